"""From a validated :class:`schemas.job.JobSpec` to a ready problem: the scene loaded at the job's
resolution, the optimized scalars with their initial values and bounds, and the target images.

Everything that can be wrong with a job and that the schema alone cannot see (an unknown key, a
wrong number of components, a target image of the wrong size) is raised here as an
:class:`InvalidJob` naming the field, before any training or rendering.

The scene of an uploaded XML job is loaded from ``scene_file``: the host has checked and staged
the uploaded files (``services.uploads``); the solver never sees untrusted paths itself.
"""

from __future__ import annotations

import base64
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import BuiltinScene, ImageTargets, JobSpec
from schemas.methods import AUTO, Method
from services.solver.estimators.methods import method_class
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import converged_depth, render
from services.solver.scene.facts import SceneFacts, probe_scene
from services.solver.scene.load import LoadedScene, load_scene
from services.solver.scene.params import ParameterSet
from services.solver.scene.planner import plan_effects
from services.solver.scene.targets import ImageDecodeError, decode_image
from services.solver.seeds import derive_seed

log = logging.getLogger(__name__)

#: Microfacet roughness below this makes the distributions degenerate (a delta peak: NaN / Inf).
MIN_ROUGHNESS = 1e-3


@dataclass
class Prepared:
    """A job ready to run: ``init``, ``lower``, ``upper`` are ``(P,)``; ``targets`` maps a sensor
    index to its ``(H, W, 3)`` target; ``target_values`` is ``(P,)`` for synthetic targets;
    ``depths`` holds the path depths of the synthetic target (``target``) and of the path-traced
    candidate and ``prb`` (``render``), and how they were chosen."""

    spec: JobSpec
    problem: Problem
    init: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    targets: dict[int, np.ndarray]
    target_values: np.ndarray | None
    depths: dict = field(default_factory=dict)
    facts: SceneFacts | None = None


def load_job_scene(spec: JobSpec, scene_file: Path | None = None) -> LoadedScene:
    """Load the job's scene: a built-in by name, anything else from ``scene_file`` (the staged
    upload, or the CLI's local file)."""
    resolution = spec.render.resolution
    try:
        if isinstance(spec.scene, BuiltinScene):
            return load_scene(builtin=spec.scene.builtin, resolution=resolution)
        if scene_file is None:
            raise InvalidJob("scene", "the scene file was not staged (a host error)")
        return load_scene(xml_path=scene_file, resolution=resolution)
    except KeyError as exc:
        raise InvalidJob("scene.builtin", str(exc.args[0])) from None
    except InvalidJob:
        raise
    except (RuntimeError, OSError, ValueError) as exc:
        raise InvalidJob("scene", f"Mitsuba could not load the scene: {exc}") from None


def _broadcast(value, size: int, field: str) -> np.ndarray:
    array = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if array.size == 1:
        return np.full(size, array[0])
    if array.size != size:
        raise InvalidJob(field, f"has {array.size} values, the parameter has {size} component(s)")
    return array


def _bounds(key: str, kind: str, bounds) -> tuple[float, float]:
    """Projection bounds: the job's, else [MIN_ROUGHNESS, 1] for a roughness, [0, 1] for other BSDF
    parameters and [0, +inf) for emitters. A roughness is never allowed below MIN_ROUGHNESS."""
    roughness = key.rsplit(".", 2)[-2] in ("alpha", "alpha_u", "alpha_v", "roughness") if "." in key else False
    if bounds is not None:
        lower, upper = float(bounds[0]), float(bounds[1])
        return (max(lower, MIN_ROUGHNESS), max(upper, MIN_ROUGHNESS)) if roughness else (lower, upper)
    if roughness:
        return MIN_ROUGHNESS, 1.0
    return (0.0, 1.0) if kind == "bsdf" else (0.0, float("inf"))


@dataclass
class Checked:
    scene: LoadedScene
    parameters: ParameterSet
    init: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    targets: dict[int, np.ndarray]
    target_values: np.ndarray | None

    def report(self) -> dict:
        """What the host needs to enforce its caps: films, sensors, scalars."""
        return {"sensors": [list(self.scene.resolution(i)) for i in range(self.scene.sensor_count)],
                "scalars": self.parameters.n, "labels": self.parameters.labels}


def check(spec: JobSpec, scene_file: Path | None = None, max_scalars: int | None = None) -> Checked:
    """Load the scene and check everything but the synthetic rendering (shared by :func:`prepare`
    and the service's preflight). Raises :class:`InvalidJob` naming the field."""
    scene = load_job_scene(spec, scene_file)
    keys = [p.key for p in spec.parameters]
    try:
        parameters = ParameterSet(scene.params, keys)
    except ValueError as exc:
        bad = [i for i, key in enumerate(keys) if f"{key!r}" in str(exc)]
        raise InvalidJob(f"parameters[{bad[0]}].key" if bad else "parameters", str(exc)) from None
    if max_scalars is not None and parameters.n > max_scalars:
        raise InvalidJob("parameters", f"{parameters.n} scalars exceed the limit of {max_scalars} "
                                       f"(an RGB value counts 3; NDRF_MAX_PARAMETERS)")
    scene_values = parameters.values()

    init, lower, upper, offset = [], [], [], 0
    for i, (p, info) in enumerate(zip(spec.parameters, parameters.infos)):
        own = scene_values[offset:offset + info.size]
        init.append(own if p.init is None else _broadcast(p.init, info.size, f"parameters[{i}].init"))
        lo, hi = _bounds(p.key, info.owner, p.bounds)
        lower.append(np.full(info.size, lo))
        upper.append(np.full(info.size, hi))
        offset += info.size
    init_v, lower_v, upper_v = np.concatenate(init), np.concatenate(lower), np.concatenate(upper)
    init_v = np.clip(init_v, lower_v, upper_v)

    targets, target_values = {}, None
    if isinstance(spec.targets, ImageTargets):
        for i, image in enumerate(spec.targets.images):
            where = f"targets.images[{i}]"
            if image.sensor >= scene.sensor_count:
                raise InvalidJob(f"{where}.sensor", f"sensor {image.sensor} does not exist; the scene has "
                                                    f"{scene.sensor_count} sensor(s)")
            if image.sensor in targets:
                raise InvalidJob(f"{where}.sensor", f"sensor {image.sensor} has two target images")
            try:
                data = decode_image(base64.b64decode(image.data, validate=True))
            except (ImageDecodeError, ValueError) as exc:
                raise InvalidJob(f"{where}.data", str(exc)) from None
            width, height = scene.resolution(image.sensor)
            if data.shape[:2] != (height, width):
                raise InvalidJob(f"{where}.data", f"image is {data.shape[1]}x{data.shape[0]}, the sensor's film is "
                                                  f"{width}x{height} (set render.resolution to match)")
            targets[image.sensor] = data
    else:
        synthetic = spec.targets.synthetic
        target_values = np.concatenate([
            _broadcast(synthetic.values[key], info.size, f"targets.synthetic.values.{key}")
            for key, info in zip(keys, parameters.infos)])
    return Checked(scene, parameters, init_v, lower_v, upper_v, targets, target_values)


def prepare(spec: JobSpec, *, scene_file: Path | None = None, method: str | None = None) -> Prepared:
    """Load and check everything a job needs, plan the effects to simulate (for ``method``,
    default the job's; ``prb``'s for an ``auto`` job until :func:`plan_for` names the choice), and
    render synthetic targets (deep enough to have converged, unless the job fixes
    ``targets.synthetic.max_depth``)."""
    c = check(spec, scene_file)
    problem = Problem(c.scene, c.parameters, delta_depth=spec.training.delta_depth)
    facts = probe_scene(c.scene, c.parameters, seed=derive_seed(spec.seed, "probe"), max_delta_depth=64)
    name = method or (Method.PRB if spec.method == AUTO else spec.method)
    problem.apply_plan(plan_effects(facts, name, method_class(name).uses, spec.effects, spec.training.delta_depth))
    for warning in problem.plan.warnings:
        log.warning("effect plan: %s", warning)
    depths = _depths(spec, problem, c)
    targets = dict(c.targets)
    if c.target_values is not None:
        c.parameters.assign(c.target_values)
        for sensor in range(c.scene.sensor_count):
            targets[sensor] = render(problem, spp=spec.targets.synthetic.spp, sensor=sensor,
                                     seed=derive_seed(spec.seed, "target", sensor), max_depth=depths["target"])
    c.parameters.assign(c.init)
    log.info("prepared job: %d scalars, %d target(s)", c.parameters.n, len(targets))
    return Prepared(spec, problem, c.init, c.lower, c.upper, targets, c.target_values, depths, facts)


def plan_for(prepared: Prepared, method: str) -> None:
    """Re-plan the prepared problem's effects for ``method`` (the scene facts are kept: no probe)."""
    if prepared.facts is None:
        raise ValueError("plan_for needs the scene facts that prepare() measured")
    spec = prepared.spec
    prepared.problem.apply_plan(plan_effects(prepared.facts, method, method_class(method).uses, spec.effects,
                                             spec.training.delta_depth))


def _depths(spec: JobSpec, problem: Problem, c: Checked) -> dict:
    """Path depths of the synthetic target and of path-traced candidates and ``prb``: the job's,
    else the depth at which the image converges (:func:`converged_depth`), measured at the target
    and at the initial parameters (the larger holds along the way between them)."""
    synthetic = None if c.target_values is None else spec.targets.synthetic
    measured: dict[str, tuple[int, float]] = {}

    def at(name: str, values: np.ndarray) -> int:
        c.parameters.assign(values)
        measured[name] = converged_depth(problem, seed=derive_seed(spec.seed, "depth", name))
        return measured[name][0]

    target = None
    if synthetic is not None:
        target = synthetic.max_depth or at("target", c.target_values)
    candidate = spec.render.max_depth or max(at("init", c.init), measured.get("target", (0, 0))[0])
    c.parameters.assign(c.init)
    reasons = {name: f"image energy converged within {missing:.1e} at depth {d} (measured at the {name} values)"
               for name, (d, missing) in measured.items()}
    return {"target": target, "render": candidate, "measured": reasons}

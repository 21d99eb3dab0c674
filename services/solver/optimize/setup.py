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
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import BuiltinScene, ImageTargets, JobSpec, SyntheticTargets
from schemas.methods import AUTO, Method
from services.solver.estimators.layout import DerivativeLayout
from services.solver.estimators.methods import method_class
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import UNBIASED, PathDepth, missing_energy, render
from services.solver.optimize.carry import check_carry, check_head
from services.solver.optimize.textures import TextureReport
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
    ``depths`` describes the path depths of the synthetic target (``target``) and of the
    path-traced candidate and ``prb`` (``render``, which is ``depth``), with any warning;
    ``seconds`` what preparing took: ``load`` (scene and checks), ``plan`` (the effect probe and
    the depth check: decisions), ``targets`` (rendering synthetic targets); the loop adds
    ``recipe`` (the recipe's measurements of the scene: closure, direct reach)."""

    spec: JobSpec
    problem: Problem
    init: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    targets: dict[int, np.ndarray]
    target_values: np.ndarray | None
    depths: dict = field(default_factory=dict)
    facts: SceneFacts | None = None
    depth: PathDepth = UNBIASED
    seconds: dict = field(default_factory=dict)
    textures: TextureReport = field(init=False)   # the listed scalars and the textures of p

    def __post_init__(self):
        self.textures = TextureReport(self.problem.parameters)


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


def _broadcast(value, size: int, field: str, channels: int | None = None) -> np.ndarray:
    """``value`` as ``(size,)``: one number broadcast, or every component; for a texture of
    ``channels`` channels also one number per channel, repeated at every texel."""
    array = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if array.size == 1:
        return np.full(size, array[0])
    if channels is not None and array.size == channels and size % channels == 0:
        return np.tile(array, size // channels)
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
        """What the host needs to enforce its caps: films, sensors, scalars (the listed ones: every
        parameter that is not a texture), texels (of the textures)."""
        listed = TextureReport(self.parameters)
        return {"sensors": [list(self.scene.resolution(i)) for i in range(self.scene.sensor_count)],
                "scalars": int(listed.listed.sum()), "labels": listed.labels, "texels": listed.texels}


def check(spec: JobSpec, scene_file: Path | None = None, max_scalars: int | None = None,
          max_texels: int | None = None) -> Checked:
    """Load the scene and check everything but the synthetic rendering (shared by :func:`prepare`
    and the service's preflight). Raises :class:`InvalidJob` naming the field."""
    scene = load_job_scene(spec, scene_file)
    keys = [p.key for p in spec.parameters]
    try:
        parameters = ParameterSet(scene.params, keys)
    except ValueError as exc:
        bad = [i for i, key in enumerate(keys) if f"{key!r}" in str(exc)]
        raise InvalidJob(f"parameters[{bad[0]}].key" if bad else "parameters", str(exc)) from None
    split = TextureReport(parameters)
    listed = int(split.listed.sum())
    if max_scalars is not None and listed > max_scalars:
        raise InvalidJob("parameters", f"{listed} scalars exceed the limit of {max_scalars} "
                                       f"(an RGB value counts 3; textures count by texel instead; NDRF_MAX_PARAMETERS)")
    if max_texels is not None and split.texels > max_texels:
        raise InvalidJob("parameters", f"the textures have {split.texels} texels, more than the limit of {max_texels} "
                                       f"(NDRF_MAX_TEXELS)")
    check_head(spec, [info.owner for info in parameters.infos])
    check_carry(spec, parameters.n, [t.key for t in split.textures])
    scene_values = parameters.values()

    init, lower, upper, offset = [], [], [], 0
    for i, (p, info) in enumerate(zip(spec.parameters, parameters.infos)):
        own = scene_values[offset:offset + info.size]
        channels = info.shape[-1] if info.shape is not None else None
        init.append(own if p.init is None else _broadcast(p.init, info.size, f"parameters[{i}].init", channels))
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
        own, offset, values = scene_values, 0, []
        for key, info in zip(keys, parameters.infos):
            value = synthetic.values[key]
            channels = info.shape[-1] if info.shape is not None else None
            values.append(own[offset:offset + info.size] if value is None else
                          _broadcast(value, info.size, f"targets.synthetic.values.{key}", channels))
            offset += info.size
        target_values = np.concatenate(values)
    return Checked(scene, parameters, init_v, lower_v, upper_v, targets, target_values)


def prepare(spec: JobSpec, *, scene_file: Path | None = None, method: str | None = None,
            on_phase: Callable[[str], None] = lambda what: None) -> Prepared:
    """Load and check everything a job needs, plan the effects to simulate (for ``method``,
    default the job's; ``prb``'s for an ``auto`` job), and render synthetic targets (unbiased:
    unbounded paths with Russian roulette, unless the job fixes ``targets.synthetic.max_depth``).
    ``on_phase`` hears what is being done, before each phase that may take long (a texture job's
    scene load and targets; the effect probe)."""
    started = time.perf_counter()
    on_phase("loading and checking the scene")
    c = check(spec, scene_file)
    loaded = time.perf_counter()
    problem = Problem(c.scene, c.parameters, delta_depth=spec.training.delta_depth)
    if not spec.effects.merge_channels:
        problem.layout = DerivativeLayout.full(c.parameters.n)
    name = method or (Method.PRB if spec.method == AUTO else spec.method)
    facts = None
    if needs_effect_plan(name, spec.jacobian) and spec.training.head is None:
        on_phase(f"probing the scene's effects for {c.parameters.n} scalars (forward-mode derivatives)")
        facts = probe_scene(c.scene, c.parameters, seed=derive_seed(spec.seed, "probe"), max_delta_depth=64)
        problem.apply_plan(plan_effects(facts, name, method_class(name).uses, spec.effects, spec.training.delta_depth))
    warnings: list[str] = []
    depths = _depths(spec, problem, c, warnings)
    for warning in problem.plan.warnings if problem.plan is not None else []:
        log.warning("effect plan: %s", warning)
    planned = time.perf_counter()
    targets = dict(c.targets)
    if c.target_values is not None:
        assert isinstance(spec.targets, SyntheticTargets)  # target values come from synthetic targets only
        synthetic = spec.targets.synthetic
        on_phase(f"rendering {c.scene.sensor_count} synthetic target(s) at {synthetic.spp} spp")
        c.parameters.assign(c.target_values)
        for sensor in range(c.scene.sensor_count):
            targets[sensor] = render(problem, spp=synthetic.spp, sensor=sensor,
                                     seed=derive_seed(spec.seed, "target", sensor), depth=depths["target"])
    c.parameters.assign(c.init)
    log.info("prepared job: %d scalars, %d target(s)", c.parameters.n, len(targets))
    described: dict = {name: depth.describe() for name, depth in depths.items()}
    if warnings:
        described["warnings"] = warnings
    seconds = {"load": loaded - started, "plan": planned - loaded, "targets": time.perf_counter() - planned}
    return Prepared(spec, problem, c.init, c.lower, c.upper, targets, c.target_values, described, facts,
                    depths["render"], seconds)


def needs_effect_plan(method: str, jacobian: str = "method") -> bool:
    """Whether a run of ``method`` needs the effect planner's probe: when it trains a field (the
    planner decides which and for which scalars). ``prb`` simulates every effect by path tracing,
    and its channel groups are known from the parameters' shapes
    (:meth:`~services.solver.estimators.layout.DerivativeLayout.by_component`)."""
    return bool(method_class(method).uses) or jacobian == "differential-field"


def plan_for(prepared: Prepared, method: str, jacobian: str = "method") -> None:
    """Plan the prepared problem's effects for ``method`` (probing the scene the first time a
    method needs the plan); nothing to do for a method that needs none."""
    spec = prepared.spec
    if not needs_effect_plan(method, jacobian) or spec.training.head is not None:
        return  # the many-parameter head simulates every effect (no per-scalar plan of P scalars)
    if prepared.facts is None:
        problem = prepared.problem
        problem.parameters.assign(prepared.init)
        prepared.facts = probe_scene(problem.scene, problem.parameters, seed=derive_seed(spec.seed, "probe"),
                                     max_delta_depth=64)
    prepared.problem.apply_plan(plan_effects(prepared.facts, method, method_class(method).uses, spec.effects,
                                             spec.training.delta_depth))


def _depths(spec: JobSpec, problem: Problem, c: Checked, warnings: list[str]) -> dict[str, PathDepth]:
    """The path depths of the synthetic target (``target``) and of the path-traced candidate,
    ``prb`` and its Jacobian (``render``): unbounded with Russian roulette unless the job fixes a
    depth. A fixed depth that misses light at the initial values is a loud warning in the plan:
    photographs have every bounce, so the optimizer would make up for the missing light with
    brighter materials."""
    depths = {"render": PathDepth(spec.render.max_depth, spec.render.rr_depth)}
    if c.target_values is not None:
        assert isinstance(spec.targets, SyntheticTargets)
        synthetic = spec.targets.synthetic
        depths["target"] = PathDepth(synthetic.max_depth, synthetic.rr_depth)
    render_depth = depths["render"]
    if not render_depth.unbiased:
        missing = missing_energy(problem, render_depth, seed=derive_seed(spec.seed, "depth"))
        if missing > 1e-3:
            warnings.append(
                f"render.max_depth {render_depth.max_depth} misses {missing:.1%} of the image's light at the initial "
                f"values (more where materials are brighter): the recovered parameters are biased; leave "
                f"render.max_depth unset for unbounded paths with Russian roulette")
            log.warning("path depth: %s", warnings[-1])
    return depths

"""From a validated :class:`schemas.job.JobSpec` to a ready problem: the scene loaded at the job's
resolution, the optimized scalars with their initial values and bounds, and the target images.

Everything that can be wrong with a job and that the schema alone cannot see is raised by
:func:`check` as an :class:`InvalidJob` naming the field, before any training or rendering: what
the scene's parameters make of the job (an unknown key, what a method or optimizer cannot carry;
the validate stage, :mod:`.validate`), then a wrong number of components or a target image of the
wrong size, as the values are read.

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
from typing import Any

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import BuiltinScene, ImageTargets, JobSpec, SyntheticTargets
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import PathDepth, missing_energy, render
from services.solver.optimize.textures import TextureReport
from services.solver.optimize.validate import validate
from services.solver.scene.closure import closure
from services.solver.scene.facts import SceneFacts, direct_reach, probe_scene
from services.solver.scene.footprint import texel_footprint
from services.solver.scene.load import LoadedScene, load_scene
from services.solver.scene.params import ParameterSet
from services.solver.scene.target_shape import own_topology, target_surface
from services.solver.scene.targets import ImageDecodeError, decode_image
from services.solver.seeds import derive_seed

log = logging.getLogger(__name__)

#: Microfacet roughness below this makes the distributions degenerate (a delta peak: NaN / Inf).
MIN_ROUGHNESS = 1e-3


@dataclass
class Prepared:
    """A job ready to be resolved and run: ``init``, ``lower``, ``upper`` are ``(P,)``; ``targets``
    maps a sensor index to its ``(H, W, 3)`` target; ``target_values`` is ``(P,)`` for synthetic
    targets (NaN in the span of a shape whose target has another topology: it has no differential
    coordinates, its surface is the mesh's ``target``); ``target_depth`` the path depth the
    synthetic targets were rendered with; ``seconds`` what preparing took: ``load`` (scene and
    checks) and ``targets`` (rendering synthetic targets). Nothing here is decided:
    :func:`services.solver.optimize.resolve.resolve` decides, from the measurements of
    :class:`SceneMeasures`."""

    spec: JobSpec
    problem: Problem
    init: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    targets: dict[int, np.ndarray]
    target_values: np.ndarray | None
    target_depth: PathDepth | None = None
    seconds: dict = field(default_factory=dict)
    textures: TextureReport = field(init=False)   # the listed scalars and the textures of p

    def __post_init__(self):
        self.textures = TextureReport(self.problem.parameters)


class SceneMeasures:
    """The measurements of a prepared job's scene that :func:`~.resolve.resolve` may ask for
    (:class:`~.rules.inputs.Measures`), each taken once, when first asked, and timed (``seconds``: the
    time deciding took, which the benchmarks charge to the product).

    ``facts``    the effect probe, at the scene file's own values (as every run has probed: a
                 checkpoint's ``dL_theta`` layout and a view of it must agree)
    ``closure``  the share of reflected light that hits another surface (geometry only)
    ``direct``   per scalar, whether it is seen directly, at the initial values
    ``missing_energy``  the share of the light a truncated path depth misses, at the initial values
    ``footprint``  per texel of a texture, the pixels of the target views that see it directly
    """

    def __init__(self, prepared: Prepared, scene_values: np.ndarray):
        self.prepared = prepared
        self.scene_values = scene_values
        self.seconds: dict[str, float] = {}
        self._taken: dict[str, object] = {}

    def _measure(self, name: str, take: Callable[[], Any]) -> Any:
        if name not in self._taken:
            started = time.perf_counter()
            self._taken[name] = take()
            self.seconds[name] = time.perf_counter() - started
        return self._taken[name]

    def facts(self) -> SceneFacts:
        prepared = self.prepared
        problem, seed = prepared.problem, prepared.spec.seed

        def probe() -> SceneFacts:
            problem.parameters.assign(self.scene_values)
            try:
                return probe_scene(problem.scene, problem.parameters, seed=derive_seed(seed, "probe"),
                                   max_delta_depth=64)
            finally:
                problem.parameters.assign(prepared.init)

        return self._measure("facts", probe)

    def closure(self) -> float | None:
        problem = self.prepared.problem
        return self._measure("closure", lambda: closure(problem.scene, seed=self.prepared.spec.seed))

    def direct(self) -> list[bool]:
        problem = self.prepared.problem
        return self._measure("direct", lambda: direct_reach(problem.scene, problem.parameters,
                                                            seed=self.prepared.spec.seed))

    def footprint(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        prepared = self.prepared
        return self._measure(f"footprint {key}", lambda: texel_footprint(prepared.problem.scene, key, shape,
                                                                         sorted(prepared.targets)))

    def film(self) -> tuple[int, int]:
        scene = self.prepared.problem.scene
        sizes = [scene.resolution(view) for view in sorted(self.prepared.targets)]
        return min(w for w, _ in sizes), min(h for _, h in sizes)

    def missing_energy(self, depth: PathDepth) -> float:
        problem = self.prepared.problem
        return self._measure(f"missing_energy {depth.describe()}", lambda: missing_energy(
            problem, depth, seed=derive_seed(self.prepared.spec.seed, "depth")))


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
    parameters, [0, +inf) for emitters and none for a pose. A roughness is never allowed below
    MIN_ROUGHNESS."""
    roughness = key.rsplit(".", 2)[-2] in ("alpha", "alpha_u", "alpha_v", "roughness") if "." in key else False
    if bounds is not None:
        lower, upper = float(bounds[0]), float(bounds[1])
        return (max(lower, MIN_ROUGHNESS), max(upper, MIN_ROUGHNESS)) if roughness else (lower, upper)
    if roughness:
        return MIN_ROUGHNESS, 1.0
    if kind == "geometry":
        return -float("inf"), float("inf")
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
                "scalars": int(listed.listed.sum()), "labels": listed.labels, "texels": listed.texels,
                "vertices": sum(mesh.size // 3 for mesh in self.parameters.shapes.values())}


def check(spec: JobSpec, scene_file: Path | None = None, max_scalars: int | None = None,
          max_texels: int | None = None) -> Checked:
    """Load the scene and check everything but the synthetic rendering (shared by :func:`prepare`
    and the service's preflight): the validate stage (:func:`~.validate.validate`), then the
    values. Raises :class:`InvalidJob` naming the field."""
    scene = load_job_scene(spec, scene_file)
    keys = [p.key for p in spec.parameters]
    try:
        parameters = ParameterSet(scene.params, keys, spec.geometry.largesteps_lambda)
    except ValueError as exc:
        bad = [i for i, key in enumerate(keys) if f"{key!r}" in str(exc)]
        raise InvalidJob(f"parameters[{bad[0]}].key" if bad else "parameters", str(exc)) from None
    validate(spec, parameters, max_scalars=max_scalars, max_texels=max_texels)
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
            mesh = parameters.shapes.get(key[:-len(".vertex_positions")]) if info.owner == "geometry" else None
            if mesh is not None:   # a shape's target surface; of its own topology, as differential coordinates
                target = synthetic.meshes.get(mesh.shape)
                mesh.target = target_surface(mesh, target, scene_file.parent if scene_file is not None else None,
                                             f"targets.synthetic.meshes.{mesh.shape}")
                values.append(mesh.to_differential(mesh.target.vertices) if own_topology(target)
                              else np.full(info.size, np.nan))
                offset += info.size
                continue
            value = synthetic.values[key]
            channels = info.shape[-1] if info.shape is not None else None
            values.append(own[offset:offset + info.size] if value is None else
                          _broadcast(value, info.size, f"targets.synthetic.values.{key}", channels))
            offset += info.size
        target_values = np.concatenate(values)
    return Checked(scene, parameters, init_v, lower_v, upper_v, targets, target_values)


def prepare(spec: JobSpec, *, scene_file: Path | None = None,
            on_phase: Callable[[str], None] = lambda what: None) -> tuple[Prepared, SceneMeasures]:
    """Load and check everything a job needs and render its synthetic targets (unbiased: unbounded
    paths with Russian roulette, unless the job fixes ``targets.synthetic.max_depth``); the scene
    is left at the initial values. Returns the prepared job and the measurements
    :func:`~.resolve.resolve` may take of its scene. ``on_phase`` hears what is being done, before
    each phase that may take long."""
    started = time.perf_counter()
    on_phase("loading and checking the scene")
    c = check(spec, scene_file)
    scene_values = c.parameters.values()
    loaded = time.perf_counter()
    problem = Problem(c.scene, c.parameters, delta_depth=spec.training.delta_depth)
    targets, target_depth = dict(c.targets), None
    if c.target_values is not None:
        assert isinstance(spec.targets, SyntheticTargets)  # target values come from synthetic targets only
        synthetic = spec.targets.synthetic
        target_depth = PathDepth(synthetic.max_depth, synthetic.rr_depth)
        on_phase(f"rendering {c.scene.sensor_count} synthetic target(s) at {synthetic.spp} spp")
        with c.parameters.showing_targets(c.target_values):   # a target mesh of another topology swapped in
            for sensor in range(c.scene.sensor_count):
                targets[sensor] = render(problem, spp=synthetic.spp, sensor=sensor,
                                         seed=derive_seed(spec.seed, "target", sensor), depth=target_depth)
    c.parameters.assign(c.init)
    log.info("prepared job: %d scalars, %d target(s)", c.parameters.n, len(targets))
    seconds = {"load": loaded - started, "targets": time.perf_counter() - loaded}
    prepared = Prepared(spec, problem, c.init, c.lower, c.upper, targets, c.target_values, target_depth, seconds)
    return prepared, SceneMeasures(prepared, scene_values)

"""From a validated :class:`schemas.job.JobSpec` to a ready problem: the scene loaded at the job's
resolution, the optimized scalars with their initial values and bounds, and the target images.

Everything that can be wrong with a job and that the schema alone cannot see (an unknown key, a
wrong number of components, a target image of the wrong size) is raised here as a
:class:`JobError` naming the field, before any training or rendering.
"""

from __future__ import annotations

import base64
import logging
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.job import BuiltinScene, ImageTargets, JobSpec, PathScene, XmlScene
from services.errors import JobError
from services.estimators.context import Problem
from services.estimators.reference import render
from services.scene.load import LoadedScene, load_scene
from services.scene.facts import probe_scene
from services.scene.params import ParameterSet
from services.scene.planner import plan_effects
from services.scene.sandbox import SandboxError, UploadLimits, check_scene_upload
from services.scene.targets import ImageDecodeError, decode_image
from services.seeds import derive_seed

log = logging.getLogger(__name__)

# The worker re-checks paths; sizes were capped by the API that accepted the job.
_UNLIMITED = UploadLimits(max_files=1 << 30, max_file_bytes=1 << 62, max_total_bytes=1 << 62, max_xml_bytes=1 << 62)


@dataclass
class Prepared:
    """A job ready to run: ``init``, ``lower``, ``upper`` are ``(P,)``; ``targets`` maps a sensor
    index to its ``(H, W, 3)`` target; ``target_values`` is ``(P,)`` for synthetic targets."""

    spec: JobSpec
    problem: Problem
    init: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    targets: dict[int, np.ndarray]
    target_values: np.ndarray | None


def load_job_scene(spec: JobSpec, base_dir: Path | None = None, folder: Path | None = None,
                   upload_limits: UploadLimits | None = None) -> LoadedScene:
    """Load the job's scene. An uploaded XML scene passes the sandbox first, every time it is
    loaded (the API at submission, the worker again before running: defence in depth), and is
    written into an emptied folder so that nothing left there can shadow an upload."""
    scene = spec.scene
    resolution = spec.render.resolution
    try:
        if isinstance(scene, BuiltinScene):
            return load_scene(builtin=scene.builtin, resolution=resolution)
        if isinstance(scene, XmlScene):
            try:
                files = check_scene_upload(scene.xml, scene.files, upload_limits or _UNLIMITED)
            except SandboxError as exc:
                raise JobError(exc.field, exc.message) from None
            if folder is not None and folder.exists():
                shutil.rmtree(folder)
            return load_scene(xml=scene.xml, files=files, folder=folder, resolution=resolution)
        if isinstance(scene, PathScene):
            path = Path(scene.path)
            if not path.is_absolute() and base_dir is not None:
                path = base_dir / path
            return load_scene(xml_path=path, resolution=resolution)
    except KeyError as exc:
        raise JobError("scene.builtin", str(exc.args[0])) from None
    except JobError:
        raise
    except (RuntimeError, OSError, ValueError) as exc:
        raise JobError("scene", f"Mitsuba could not load the scene: {exc}") from None
    raise JobError("scene", f"unsupported scene source {type(scene).__name__}")


def _broadcast(value, size: int, field: str) -> np.ndarray:
    array = np.atleast_1d(np.asarray(value, dtype=np.float64))
    if array.size == 1:
        return np.full(size, array[0])
    if array.size != size:
        raise JobError(field, f"has {array.size} values, the parameter has {size} component(s)")
    return array


#: Microfacet roughness below this makes the distributions degenerate (a delta peak: NaN / Inf).
MIN_ROUGHNESS = 1e-3


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


def _check(spec: JobSpec, base_dir: Path | None, folder: Path | None, max_scalars: int | None = None,
           upload_limits: UploadLimits | None = None):
    """Load the scene and check everything but the synthetic rendering (shared by :func:`prepare`
    and :func:`preflight`)."""
    scene = load_job_scene(spec, base_dir, folder, upload_limits)
    keys = [p.key for p in spec.parameters]
    try:
        parameters = ParameterSet(scene.params, keys)
    except ValueError as exc:
        bad = [i for i, key in enumerate(keys) if f"{key!r}" in str(exc)]
        raise JobError(f"parameters[{bad[0]}].key" if bad else "parameters", str(exc)) from None
    if max_scalars is not None and parameters.n > max_scalars:
        raise JobError("parameters", f"{parameters.n} scalars exceed the limit of {max_scalars} "
                                     f"(an RGB value counts 3)")
    scene_values = parameters.values()

    init, lower, upper, offset = [], [], [], 0
    for i, (p, info) in enumerate(zip(spec.parameters, parameters.infos)):
        own = scene_values[offset:offset + info.size]
        init.append(own if p.init is None else _broadcast(p.init, info.size, f"parameters[{i}].init"))
        lo, hi = _bounds(p.key, info.owner, p.bounds)
        lower.append(np.full(info.size, lo))
        upper.append(np.full(info.size, hi))
        offset += info.size
    init, lower, upper = np.concatenate(init), np.concatenate(lower), np.concatenate(upper)
    init = np.clip(init, lower, upper)

    targets, target_values = {}, None
    if isinstance(spec.targets, ImageTargets):
        for i, image in enumerate(spec.targets.images):
            field = f"targets.images[{i}]"
            if image.sensor >= scene.sensor_count:
                raise JobError(f"{field}.sensor", f"sensor {image.sensor} does not exist; the scene has "
                                                  f"{scene.sensor_count} sensor(s)")
            if image.sensor in targets:
                raise JobError(f"{field}.sensor", f"sensor {image.sensor} has two target images")
            try:
                data = decode_image(base64.b64decode(image.data, validate=True))
            except (ImageDecodeError, ValueError) as exc:
                raise JobError(f"{field}.data", str(exc)) from None
            width, height = scene.resolution(image.sensor)
            if data.shape[:2] != (height, width):
                raise JobError(f"{field}.data", f"image is {data.shape[1]}x{data.shape[0]}, the sensor's film is "
                                                f"{width}x{height} (set render.resolution to match)")
            targets[image.sensor] = data
    else:
        synthetic = spec.targets.synthetic
        target_values = np.concatenate([
            _broadcast(synthetic.values[key], info.size, f"targets.synthetic.values.{key}")
            for key, info in zip(keys, parameters.infos)])
    return scene, parameters, init, lower, upper, targets, target_values


def preflight(spec: JobSpec, folder: Path | None = None, max_scalars: int | None = None,
              upload_limits: UploadLimits | None = None) -> None:
    """Every check :func:`prepare` makes, without training or rendering (the API runs it at
    submission, so a bad job is a 4xx and not a failed job). Raises :class:`JobError`."""
    _check(spec, None, folder, max_scalars, upload_limits)


def prepare(spec: JobSpec, *, base_dir: Path | None = None, folder: Path | None = None,
            method: str | None = None) -> Prepared:
    """Load and check everything a job needs, plan the effects to simulate (for ``method``,
    default the job's), and render synthetic targets."""
    scene, parameters, init, lower, upper, targets, target_values = _check(spec, base_dir, folder)
    problem = Problem(scene, parameters, delta_depth=spec.training.delta_depth)
    facts = probe_scene(scene, parameters, seed=derive_seed(spec.seed, "probe"), max_delta_depth=64)
    problem.apply_plan(plan_effects(facts, method or spec.method, spec.effects, spec.training.delta_depth))
    for warning in problem.plan.warnings:
        log.warning("effect plan: %s", warning)
    if target_values is not None:
        parameters.assign(target_values)
        for sensor in range(scene.sensor_count):
            targets[sensor] = render(problem, spp=spec.targets.synthetic.spp,
                                     seed=derive_seed(spec.seed, "target", sensor), sensor=sensor,
                                     max_depth=spec.render.max_depth)
    parameters.assign(init)
    log.info("prepared job: %d scalars, %d target(s)", parameters.n, len(targets))
    return Prepared(spec, problem, init, lower, upper, targets, target_values)

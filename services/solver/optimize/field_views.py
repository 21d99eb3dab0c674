"""Views of a job's trained fields from any camera (paper Sec. 7.1, Fig. 4b).

``dL_theta`` solves the differential rendering equation everywhere in the scene, not for one
camera: queried at the first hits of any camera's rays it gives that camera's gradient images
without path tracing (Eq. 11), exactly as ``ndrf-lhs`` reads it at the job's own sensors. With
``K = W·H·spp`` fixed rays of the view's camera (first non-delta hit ``x_k``, sensor weight and
delta throughput ``w_k β_k``):

    radiance[h, w]       = mean_k∈pixel  w_k β_k [E(x_k) + L_phi(x_k, ω_o)]           (H, W, 3)   (Eq. 1)
    gradients[p, h, w]   = mean_k∈pixel  w_k β_k [∂_p E(x_k) + dL_theta_p(x_k, ω_o)]   (P, H, W, 3) (Eq. 11)
    prb[p, h, w]         = ∂I/∂p by Mitsuba's prb in forward mode, same camera           (P, H, W, 3)

(:class:`~services.solver.estimators.first_hits.FirstHitCache` on the scene rebuilt with the
camera appended: :mod:`services.solver.scene.cameras`). Scalars the job's chosen effects left
inactive have zero images in both.

:func:`restore` rebuilds the fields from a checkpoint's bytes (the job's own fingerprint checked);
:func:`render_view` renders one camera. Both are pure computations: the caller writes the files.
"""

from __future__ import annotations

import dataclasses
import io
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
import numpy as np
import torch

from schemas.job import JobSpec
from schemas.methods import Method
from schemas.views import ViewRequest
from services.solver.estimators.methods import Fields, make_method
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import PathDepth
from services.solver.optimize.build import apply_effects
from services.solver.optimize.recipe import Recipe
from services.solver.optimize.resolve import resolve
from services.solver.optimize.setup import Prepared, SceneMeasures, check
from services.solver.scene.cameras import moved_sensor, perspective, sensor_pose, with_cameras
from services.solver.scene.load import LoadedScene
from services.solver.scene.params import ParameterSet
from services.solver.seeds import derive_seed
from services.solver.training.trainer import FieldTrainer, layout_json

log = logging.getLogger(__name__)


def read_state(blob: bytes) -> dict:
    """A checkpoint's contents (tensors and plain data only; torch's RNG state untouched)."""
    return torch.load(io.BytesIO(blob), map_location="cpu", weights_only=True)


@dataclass
class Restored:
    """A job's fields as its checkpoint left them, on the job's scene.

    problem     the job's scene and scalars, planned as the run planned them
    trainer     the fields (``trainer.queried()`` is what gradients read)
    values      ``(P,)`` the checkpoint's parameters (assigned to the scene)
    iteration   the checkpoint's next iteration; ``method`` the method that ran
    """

    spec: JobSpec
    problem: Problem
    trainer: FieldTrainer
    values: np.ndarray
    iteration: int
    method: str
    depth: PathDepth
    seconds: float


def planned_problem(spec: JobSpec, method: str, scene_file: Path | None = None) -> tuple[Prepared, Recipe]:
    """The job's scene and scalars with the effects a run of ``method`` chose (the probe is seeded
    by the job: the same effects, hence the same ``dL_theta`` outputs, as the run's), without
    rendering targets."""
    c = check(spec, scene_file)
    problem = Problem(c.scene, c.parameters, delta_depth=spec.training.delta_depth)
    prepared = Prepared(spec, problem, c.init, c.lower, c.upper, {}, c.target_values)
    measures = SceneMeasures(prepared, c.parameters.values())
    ran = spec.model_copy(update={"method": method})
    recipe = resolve(ran, c.parameters, max(1, c.scene.sensor_count), measures)
    apply_effects(prepared, recipe)
    prepared.problem.parameters.assign(c.init)
    return prepared, recipe


def check_layout(problem: Problem, saved: dict, field: str = "checkpoint") -> None:
    """Raise ``ValueError`` if the checkpointed fields' derivative layout (which scalar and channel
    each output of ``dL_theta`` is) differs from ``problem``'s: the outputs would be read as the
    wrong scalars. Checkpoints from before the layout was saved are not checked."""
    layout = saved.get("layout")
    if layout is not None and layout != layout_json(problem.layout):
        raise ValueError(f"the {field}'s dL_theta has another layout of scalars and channels ({layout}; this job: "
                         f"{layout_json(problem.layout)}): its chosen effects differ")


def restore(spec: JobSpec, blob: bytes, scene_file: Path | None = None, *, train: bool = False) -> Restored:
    """The fields of the checkpoint ``blob`` of the job ``spec``. Raises ``ValueError`` if the
    checkpoint is another job's or holds no field (a ``prb`` or ``direct`` run trains none).
    ``train`` false: the trainer has no residual pool (a view only queries the fields)."""
    started = time.perf_counter()
    state = read_state(blob)
    if state.get("fingerprint") != spec.fingerprint():
        raise ValueError("the checkpoint belongs to a different job specification")
    saved = state.get("trainer")
    method = str(state.get("method") or spec.method)
    if not saved or not saved.get("fields"):
        raise ValueError(f"the job's run ({method}) trained no field: nothing to view (prb and direct train none)")
    prepared, recipe = planned_problem(spec, method, scene_file)
    check_layout(prepared.problem, saved)
    config = spec.training if train else spec.training.model_copy(
        update={"pool": spec.training.pool.model_copy(update={"enabled": False})})
    trainer = FieldTrainer(prepared.problem, config, radiance="radiance" in saved["fields"],
                           differential="differential" in saved["fields"], seed=spec.seed)
    try:
        trainer.load_state_dict(saved)
    except RuntimeError as exc:  # a size mismatch: another plan, or another field configuration
        raise ValueError(f"the checkpoint's fields do not fit the job's plan: {exc}") from None
    values = np.asarray(state["parameters"], np.float64)
    prepared.problem.parameters.assign(values)
    return Restored(spec, prepared.problem, trainer, values, int(state["next_iteration"]), method, recipe.depth,
                    time.perf_counter() - started)


@dataclass
class FieldView:
    """One camera's images (module docstring): ``radiance`` ``(H, W, 3)``, ``gradients`` and
    ``prb`` ``(P, H, W, 3)`` float32, the scalars' labels, seconds per phase."""

    radiance: np.ndarray
    gradients: np.ndarray
    prb: np.ndarray | None
    scalars: list[str]
    seconds: dict[str, float]
    camera: dict


def camera_for(loaded: LoadedScene, request: ViewRequest, default: tuple[int, int] | None) -> tuple[mi.Sensor, dict]:
    """The request's camera and its description (resolution: the request's, else ``default``,
    else the film of the sensor moved). Raises ``ValueError`` for a camera that cannot be built."""
    if request.sensor is not None:
        if request.sensor >= loaded.sensor_count:
            raise ValueError(f"sensor {request.sensor} does not exist; the scene has {loaded.sensor_count} sensor(s)")
        width, height = request.resolution or loaded.resolution(request.sensor)
        camera = moved_sensor(loaded, request.sensor, request.offset, width, height)
        pose = sensor_pose(loaded, request.sensor, request.offset)
        return camera, {"sensor": request.sensor, "offset": list(request.offset), "resolution": [width, height],
                        **pose}
    assert request.origin is not None and request.target is not None  # the schema requires a camera
    width, height = request.resolution or default or loaded.resolution(0)
    camera = perspective(request.origin, request.target, request.up, request.fov, width, height)
    return camera, {"origin": list(request.origin), "target": list(request.target), "up": list(request.up),
                    "fov": request.fov, "resolution": [width, height]}


def render_view(restored: Restored, request: ViewRequest) -> FieldView:
    """Render the restored fields from the request's camera (and ``prb`` when ``prb_spp``)."""
    from services.solver.estimators.first_hits import FirstHitCache

    started = time.perf_counter()
    base = restored.problem
    camera, described = camera_for(base.scene, request, restored.spec.render.resolution)
    scene = with_cameras(base.scene, [camera])
    parameters = ParameterSet(scene.params, base.parameters.keys, restored.spec.geometry.largesteps_lambda)
    problem = dataclasses.replace(base, scene=scene, parameters=parameters, sanitized={})
    problem.layout = base.layout
    parameters.assign(restored.values)
    index = scene.sensor_count - 1
    fields = restored.trainer.queried()
    queried = [f for f in (fields.radiance, fields.differential) if f is not None]
    built = time.perf_counter()
    cache = FirstHitCache(problem, [index], request.spp, derive_seed(request.seed, "view"), queried)
    radiance = cache.candidate(index, fields.radiance)
    gradients = cache.gradient_images(index, fields.differential)
    done = time.perf_counter()
    prb = None
    if request.prb_spp is not None:
        method = make_method(Method.PRB, problem.effects, restored.depth)
        prb = method.gradient_images(problem, Fields(), spp=request.prb_spp, seed=derive_seed(request.seed, "prb"),
                            sensor=index)
    seconds = {"scene": built - started, "fields": done - built, "prb": time.perf_counter() - done}
    if problem.sanitized:
        log.warning("view: non-finite values zeroed: %s", problem.sanitized)
    return FieldView(np.asarray(radiance, np.float32), np.asarray(gradients, np.float32),
                     None if prb is None else np.asarray(prb, np.float32), list(parameters.labels), seconds,
                     described)

"""Caps on untrusted jobs (pure logic; the API maps a violation to a 4xx naming the limit).

:func:`check_limits` sees the job file alone; :func:`check_scene_report` sees what the sandboxed
loader read from the scene itself (films, sensors), since a cap must hold where the work is
decided, not where a field happens to be: a job that omits ``render.resolution`` renders the
XML's film.
"""

from __future__ import annotations

import base64
import binascii

from schemas.errors import InvalidJob
from schemas.job import ImageTargets, JobSpec, PathScene, SyntheticTargets
from schemas.methods import AUTO, Method
from schemas.solver import FieldConfig
from services.settings import Limits


def field_parameters(config: FieldConfig, outputs: int) -> int:
    """Learned numbers of one field: hash tables (dense levels count their vertices) and MLP."""
    grid = config.encoding
    table = 1 << grid.log2_hashmap_size
    entries = sum(min(table, (int(grid.base_resolution * grid.per_level_scale ** level) + 1) ** 3)
                  for level in range(grid.n_levels))
    width, layers = config.mlp.hidden_width, config.mlp.hidden_layers
    inputs = grid.output_dim + config.direction_sh_degree ** 2 + 3
    mlp = (inputs + 1) * width + (layers - 1) * (width + 1) * width + (width + 1) * outputs
    return entries * grid.features_per_level + mlp


def check_limits(spec: JobSpec, limits: Limits) -> None:
    """Raise :class:`InvalidJob` for the first field over a cap (or a source the service refuses)."""
    if isinstance(spec.scene, PathScene):
        raise InvalidJob("scene.path", "the service does not read host paths: send {'xml': ..., 'files': {...}} "
                                       "(ndrf submit packs a local scene)")
    if spec.render.resolution is not None:
        width, height = spec.render.resolution
        if max(width, height) > limits.resolution:
            raise InvalidJob("render.resolution", f"{width}x{height} exceeds the limit of {limits.resolution} "
                                                  f"pixels per side (NDRF_MAX_RESOLUTION)")
    for field, spp in (("render.spp", spec.render.spp), ("render.gradient_spp", spec.render.gradient_spp)):
        if spp > limits.spp:
            raise InvalidJob(field, f"{spp} exceeds the limit of {limits.spp} samples per pixel (NDRF_MAX_SPP)")
    if isinstance(spec.targets, SyntheticTargets) and spec.targets.synthetic.spp > limits.spp:
        raise InvalidJob("targets.synthetic.spp", f"{spec.targets.synthetic.spp} exceeds the limit of {limits.spp} "
                                                  f"samples per pixel (NDRF_MAX_SPP)")
    if spec.iterations > limits.iterations:
        raise InvalidJob("iterations", f"{spec.iterations} exceeds the limit of {limits.iterations} "
                                       f"(NDRF_MAX_ITERATIONS)")
    if len(spec.parameters) > limits.parameters:
        raise InvalidJob("parameters", f"{len(spec.parameters)} parameters exceed the limit of {limits.parameters} "
                                       f"scalars (NDRF_MAX_PARAMETERS)")
    training = spec.training
    lanes = training.residual_points * training.incident_samples
    if lanes > limits.training_points:
        raise InvalidJob("training.residual_points", f"N x M = {lanes} exceeds the limit of {limits.training_points} "
                                                     f"(NDRF_MAX_TRAINING_POINTS)")
    steps = training.warmup_steps + spec.iterations * training.steps_per_iteration
    if steps > limits.training_steps:
        raise InvalidJob("training.steps_per_iteration", f"warm-up + iterations x steps per iteration = {steps} "
                                                         f"training steps exceed the limit of {limits.training_steps} "
                                                         f"(NDRF_MAX_TRAINING_STEPS)")
    outputs = 3 * limits.parameters
    for name, config in (("radiance", training.radiance), ("differential", training.differential)):
        size = field_parameters(config, 3 if name == "radiance" else outputs)
        if size > limits.field_parameters:
            raise InvalidJob(f"training.{name}", f"the field would learn {size} numbers, more than the limit of "
                                                 f"{limits.field_parameters} (NDRF_MAX_FIELD_PARAMETERS): use a "
                                                 f"smaller hash table, fewer levels or a narrower network")
    if isinstance(spec.targets, ImageTargets):
        for i, image in enumerate(spec.targets.images):
            if len(image.data) * 3 // 4 > limits.upload_bytes:
                raise InvalidJob(f"targets.images[{i}].data",
                                 f"image exceeds the upload limit of {limits.upload_bytes} bytes")


def check_target_headers(spec: JobSpec, limits: Limits) -> None:
    """Refuse target images whose header declares more pixels than ``NDRF_MAX_IMAGE_PIXELS``, or
    more decoded values (pixels x channels) than ``NDRF_MAX_IMAGE_VALUES``, before any decoder
    allocates for them (:func:`services.uploads.images.check_image`)."""
    from services.uploads.images import check_image

    if not isinstance(spec.targets, ImageTargets):
        return
    for i, image in enumerate(spec.targets.images):
        where = f"targets.images[{i}].data"
        try:
            head = base64.b64decode(image.data[:65536 - 65536 % 4], validate=True)
        except (binascii.Error, ValueError):
            raise InvalidJob(where, "is not valid base64") from None
        check_image(where, head, limits.image_pixels, max_values=limits.image_values,
                    values_name="NDRF_MAX_IMAGE_VALUES")


#: Seconds of a shape job's set-up per vertex it optimizes, to its first iteration: 38.1 s for
#: 399,425 vertices on the 2-core CPU (``python -m bench.big_mesh``; set-up is linear in the
#: vertices since #46), rounded up.
SETUP_SECONDS_PER_VERTEX = 1e-4
#: The share of the job budget (``NDRF_MAX_JOB_SECONDS``) its set-up may be estimated to take.
SETUP_SHARE = 0.5


def check_setup(spec: JobSpec, vertices: int, limits: Limits) -> None:
    """Refuse a job whose set-up alone is estimated to take more than :data:`SETUP_SHARE` of its
    budget, naming the field to change (a job that could not reach its first iteration would hold
    a worker for the whole budget and return nothing)."""
    estimate = vertices * SETUP_SECONDS_PER_VERTEX
    if estimate > SETUP_SHARE * limits.job_seconds:
        keys = [p.key for p in spec.parameters if p.key.endswith(".vertex_positions")]
        raise InvalidJob("parameters", f"{', '.join(keys) or 'the meshes'}: {vertices} vertices to optimize, whose "
                                       f"set-up is estimated at {estimate:.0f} s, more than {SETUP_SHARE:g} of the job "
                                       f"budget of {limits.job_seconds:g} s (NDRF_MAX_JOB_SECONDS); optimize a coarser "
                                       f"mesh (fewer vertices) or raise the budget")


#: The share of the job budget its first iteration may be estimated to take.
FIRST_ITERATION_SHARE = 0.5
#: The methods whose first iteration :func:`first_iteration_samples` prices: each sample a traced
#: path (``auto`` resolves to one of them but in closed scenes, where ``ndrf-lhs`` is cheaper).
TRACED_METHODS = (AUTO, Method.PRB, Method.PRB_PROJECTIVE, Method.DIRECT_PROJECTIVE)
#: The optimizers whose steps need the Jacobian, measured at the first iteration's views.
JACOBIAN_OPTIMIZERS = ("levenberg-marquardt", "gauss-newton")


def first_iteration_samples(spec: JobSpec, sensors: list, scalars: int, every_view: bool) -> tuple[int, int, int]:
    """Samples the first iteration of a path-traced job traces, at least, as ``(pixels, per
    pixel, Jacobian renders per view)`` (``bench/first_iteration.py`` times them): the films of
    its first batch of views (``auto``: one, or every view with ``every_view``, a mesh's or a
    texture's job; the smallest films, as the batch is drawn) times the samples per pixel of each view's renders: under Adam
    one differentiable render, the mean of ``spp`` (its primal pass) and ``gradient_spp`` (its
    adjoint replay), which together cost about one forward-mode sample; under an explicit
    Levenberg-Marquardt or Gauss-Newton, ``gradient_spp`` for each forward-mode render of the
    Jacobian (one per channel group: at least a third of the scalars, one R, one G and one B per
    group) and ``spp`` for the candidate when it differs. The recipe may raise a geometry job's
    spp or pick Levenberg-Marquardt under ``auto``: never below this count. Zero for the field
    methods (their cost is the training, capped by ``NDRF_MAX_TRAINING_*``)."""
    if spec.method not in TRACED_METHODS or not sensors:
        return 0, 0, 0
    render, views = spec.render, spec.views_per_iteration
    count = (len(sensors) if every_view else 1) if views == "auto" else min(int(views), len(sensors))
    pixels = sum(sorted(int(w) * int(h) for w, h in sensors)[:count])
    if spec.optimizer in JACOBIAN_OPTIMIZERS and spec.jacobian == "method":
        groups = max(1, -(-scalars // 3))
        return pixels, groups * render.gradient_spp + (render.spp if render.spp != render.gradient_spp else 0), groups
    return pixels, (render.spp + render.gradient_spp + 1) // 2, 0


def check_first_iteration(spec: JobSpec, report: dict, limits: Limits) -> None:
    """Refuse a path-traced job whose first iteration is estimated to take more than
    :data:`FIRST_ITERATION_SHARE` of its budget, at ``NDRF_MAX_WORKER_SAMPLES_PER_SECOND``,
    naming the field to change: films, spp, views and scalars can each pass their caps and
    together need hours for one iteration, holding a worker for the budget to return nothing.
    The field: the Jacobian's (``parameters``) or the spp that dominates, else, when the job
    would not fit even at 1 spp, ``render.resolution``."""
    sensors = report["sensors"]
    every_view = bool(report.get("vertices") or report.get("texels"))   # a mesh's or a texture's job
    pixels, per_pixel, groups = first_iteration_samples(spec, sensors, int(report.get("scalars") or 0), every_view)
    rate, most = limits.worker_samples_per_second, FIRST_ITERATION_SHARE * limits.job_seconds
    estimate = pixels * per_pixel / rate
    if estimate <= most:
        return
    render = spec.render
    if pixels / rate > most:
        field = "render.resolution"
    elif groups * render.gradient_spp >= render.spp:
        field = "parameters" if groups > 1 and pixels * render.gradient_spp / rate <= most else "render.gradient_spp"
    else:
        field = "render.spp" if render.spp >= render.gradient_spp else "render.gradient_spp"
    films = ", ".join(f"{w}x{h}" for w, h in sensors[:4]) + (", ..." if len(sensors) > 4 else "")
    jacobian = f", {groups} Jacobian renders per view ({report.get('scalars')} scalars)" if groups else ""
    raise InvalidJob(field, f"the first iteration would trace {pixels * per_pixel:.3g} samples ({pixels} pixels of "
                            f"its first views, films {films}, x {per_pixel} per pixel: spp {render.spp}, gradient_spp "
                            f"{render.gradient_spp}{jacobian}), estimated at {estimate:.0f} s at {rate:g} samples per "
                            f"second (NDRF_MAX_WORKER_SAMPLES_PER_SECOND), more than {FIRST_ITERATION_SHARE:g} of the "
                            f"job budget of {limits.job_seconds:g} s (NDRF_MAX_JOB_SECONDS); lower {field} or raise "
                            f"the budget")


def check_scene_report(spec: JobSpec, report: dict, limits: Limits) -> None:
    """Caps on what the sandboxed loader read from the scene: sensors and their films (after
    the job's ``render.resolution``), the samples they imply, the set-up its meshes need
    (:func:`check_setup`) and the cost of its first iteration (:func:`check_first_iteration`)."""
    check_setup(spec, int(report.get("vertices") or 0), limits)
    sensors = report["sensors"]
    if len(sensors) > limits.sensors:
        raise InvalidJob("scene", f"the scene has {len(sensors)} sensors, more than the limit of {limits.sensors} "
                                  f"(NDRF_MAX_SENSORS)")
    for i, (width, height) in enumerate(sensors):
        if max(width, height) > limits.resolution:
            field = "render.resolution" if spec.render.resolution is not None else "scene"
            raise InvalidJob(field, f"sensor {i} has a film of {width}x{height}, over the limit of {limits.resolution} "
                                    f"pixels per side (NDRF_MAX_RESOLUTION); set render.resolution")
    check_first_iteration(spec, report, limits)

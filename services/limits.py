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
from schemas.solver import FieldConfig, TrainingConfig
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
#: The share of the job budget (``NDRF_MAX_JOB_SECONDS``) its set-up and first iteration, together,
#: may be estimated to take (:func:`check_first_iteration`).
FIRST_ITERATION_SHARE = 0.5
#: Samples of the worker's rate one sample of a synthetic target costs: a primal path of the
#: same unbounded depth, without the adjoint replay a sample of :func:`first_iteration_samples`
#: includes. The demo's Cornell box at 256x256 and 16 spp rendered 9.4e5 to 1.1e6 samples per
#: second, prb's first iteration 3.6e5 to 5.2e5 in the same session (2-core CPU shared with other
#: work): against the default rate of 5e5, 0.53 of a sample, rounded down.
TARGET_SAMPLE_COST = 0.5
#: Samples of the worker's rate one incident sample of the warm-up costs (``training.residual_points``
#: x ``training.incident_samples`` per step: a hit, an emitter and a BSDF sample, the fields'
#: forward and backward passes). On the demo (64x64, default training, 2-core CPU shared with other
#: work) ndrf-lhs trained 2.5e4 incident samples per second (100 and 200 warm-up steps: 71 and 132
#: s) and radiance-cache (one field) 4.1e4, where prb traced 3.6e5 to 5.2e5 samples per second:
#: 8.8 to 21 samples each, rounded down to 8 so that the estimate errs short, never refusing a
#: warm-up that fits (docs/guide/service.md).
TRAINING_SAMPLE_COST = 8.0
#: The methods whose first iteration :func:`first_iteration_samples` prices as traced paths (``auto``
#: resolves to one of them but in closed scenes, where ``ndrf-lhs`` is cheaper).
TRACED_METHODS = (AUTO, Method.PRB, Method.PRB_PROJECTIVE, Method.DIRECT_PROJECTIVE)
#: The methods that train fields before their first gradient (``direct`` trains none).
FIELD_METHODS = (Method.NDRF_LHS, Method.NDRF_RHS, Method.RADIANCE_CACHE)
#: The optimizers whose steps need the Jacobian, measured at the first iteration's views.
JACOBIAN_OPTIMIZERS = ("levenberg-marquardt", "gauss-newton")


def target_samples(spec: JobSpec, sensors: list) -> int:
    """Samples the set-up traces for the synthetic targets: every sensor's film (after
    ``render.resolution``) at ``targets.synthetic.spp``; none for uploaded images."""
    if not isinstance(spec.targets, SyntheticTargets):
        return 0
    return sum(int(w) * int(h) for w, h in sensors) * spec.targets.synthetic.spp


def warmup_steps(spec: JobSpec) -> int:
    """Training steps before the first gradient, each of ``training.residual_points`` x
    ``training.incident_samples`` incident samples: ``training.warmup_steps`` (adaptive: at most),
    with ``warm_start`` its top-up (``top_up_steps``, or a quarter of the warm-up), when the job
    trains a field (a field method, the field's candidate or Jacobian, the many-parameter head);
    0 otherwise."""
    training = spec.training
    if not (spec.method in FIELD_METHODS or spec.render.candidate == "field" or spec.jacobian == "differential-field"
            or training.head is not None):
        return 0
    if spec.warm_start is not None:
        top_up = spec.warm_start.top_up_steps
        return top_up if top_up is not None else training.warmup_steps // 4
    return training.warmup_steps


def first_iteration_samples(spec: JobSpec, sensors: list, scalars: int, every_view: bool) -> tuple[int, int, int]:
    """Samples the first iteration's renders trace, at least, as ``(pixels, per pixel, Jacobian
    renders per view)`` (``bench/first_iteration.py`` times them): the films of its first batch
    of views (``auto``: one, or every view with ``every_view``, a mesh's or a texture's job; the
    smallest films, as the batch is drawn) times the samples per pixel of each view's renders:
    under Adam one differentiable render, the mean of ``spp`` (its primal pass) and
    ``gradient_spp`` (its adjoint replay), which together cost about one forward-mode sample;
    under an explicit Levenberg-Marquardt or Gauss-Newton, ``gradient_spp`` for each forward-mode
    render of the Jacobian (one per channel group: at least a third of the scalars, one R, one G
    and one B per group) and ``spp`` for the candidate when it differs. The recipe may raise a
    geometry job's spp or pick Levenberg-Marquardt under ``auto``: never below this count. The
    field methods and ``direct`` as under Adam (a path-traced candidate, a camera-hit query; their
    Jacobian is a field query): their training is :func:`warmup_steps`."""
    if not sensors:
        return 0, 0, 0
    render, views = spec.render, spec.views_per_iteration
    count = (len(sensors) if every_view else 1) if views == "auto" else min(int(views), len(sensors))
    pixels = sum(sorted(int(w) * int(h) for w, h in sensors)[:count])
    traced = spec.method in TRACED_METHODS
    if traced and spec.optimizer in JACOBIAN_OPTIMIZERS and spec.jacobian == "method":
        groups = max(1, -(-scalars // 3))
        return pixels, groups * render.gradient_spp + (render.spp if render.spp != render.gradient_spp else 0), groups
    candidate = render.spp if traced or render.candidate == "path" else 0
    return pixels, (candidate + render.gradient_spp + 1) // 2, 0


def _render_field(spec: JobSpec, pixels: int, groups: int, rate: float, left: float) -> str:
    """The field that lowers the first iteration's renders: the Jacobian's (``parameters``) or the
    spp that dominates, else, when they would not fit even at 1 spp, ``render.resolution``."""
    render = spec.render
    if pixels / rate > left:
        return "render.resolution"
    if groups * render.gradient_spp >= render.spp:
        return "parameters" if groups > 1 and pixels * render.gradient_spp / rate <= left else "render.gradient_spp"
    return "render.spp" if render.spp >= render.gradient_spp else "render.gradient_spp"


def check_first_iteration(spec: JobSpec, report: dict, limits: Limits) -> None:
    """Refuse a job whose set-up and first iteration together are estimated to take more than
    :data:`FIRST_ITERATION_SHARE` of its budget, at ``NDRF_MAX_WORKER_SAMPLES_PER_SECOND``,
    naming the field of the largest term to change: films, spp, views, scalars, vertices and
    training can each pass their caps and together need hours before one iteration, holding a
    worker for the budget to return nothing. The terms: the meshes' set-up
    (:data:`SETUP_SECONDS_PER_VERTEX`), the synthetic targets (:func:`target_samples`), the
    renders (:func:`first_iteration_samples`) and the warm-up training (:func:`warmup_steps`)."""
    sensors, vertices = report["sensors"], int(report.get("vertices") or 0)
    every_view = bool(vertices or report.get("texels"))   # a mesh's or a texture's job
    pixels, per_pixel, groups = first_iteration_samples(spec, sensors, int(report.get("scalars") or 0), every_view)
    rate, most = limits.worker_samples_per_second, FIRST_ITERATION_SHARE * limits.job_seconds
    render, training = spec.render, spec.training
    steps = warmup_steps(spec)
    targets, lanes = target_samples(spec, sensors), steps * training.residual_points * training.incident_samples
    target_spp = spec.targets.synthetic.spp if isinstance(spec.targets, SyntheticTargets) else 0
    films = ", ".join(f"{w}x{h}" for w, h in sensors[:4]) + (", ..." if len(sensors) > 4 else "")
    keys = [p.key for p in spec.parameters if p.key.endswith(".vertex_positions")]
    jacobian = f", {groups} Jacobian renders per view ({report.get('scalars')} scalars)" if groups else ""
    terms = {   # field -> (seconds, what was counted)
        "parameters": (vertices * SETUP_SECONDS_PER_VERTEX,
                       f"{', '.join(keys) or 'the meshes'}: {vertices} vertices to optimize (a coarser mesh has "
                       f"fewer), whose set-up"),
        "targets.synthetic.spp": (targets * TARGET_SAMPLE_COST / rate,
                                  f"the synthetic targets' {targets:.3g} samples ({len(sensors)} sensors, films "
                                  f"{films}, x spp {target_spp})"),
        "render": (pixels * per_pixel / rate,
                   f"the first iteration's {pixels * per_pixel:.3g} samples ({pixels} pixels of its first views, "
                   f"films {films}, x {per_pixel} per pixel: spp {render.spp}, gradient_spp "
                   f"{render.gradient_spp}{jacobian})"),
        "training": (lanes * TRAINING_SAMPLE_COST / rate,
                     f"the warm-up's {lanes:.3g} incident samples ({steps} steps x "
                     f"residual_points {training.residual_points} x incident_samples {training.incident_samples}, "
                     f"each {TRAINING_SAMPLE_COST:g} samples)")}
    estimate = sum(seconds for seconds, _ in terms.values())
    if estimate <= most:
        return
    largest = max(terms, key=lambda name: terms[name][0])
    left = most - (estimate - terms[largest][0])
    field = largest
    if largest == "targets.synthetic.spp" and targets // target_spp * TARGET_SAMPLE_COST / rate > left:
        field = "render.resolution"     # not even at 1 spp
    elif largest == "render":
        field = _render_field(spec, pixels, groups, rate, left)
    elif largest == "training":         # the factor further above its default
        defaults = TrainingConfig()
        batch = training.residual_points * training.incident_samples
        field = "warm_start.top_up_steps" if spec.warm_start is not None else "training.warmup_steps" \
            if steps / defaults.warmup_steps >= batch / (defaults.residual_points * defaults.incident_samples) \
            else "training.residual_points"
    counted = "; ".join(f"{what} {seconds:.0f} s" for seconds, what in terms.values() if seconds >= 0.5)
    raise InvalidJob(field, f"set-up and first iteration estimated at {estimate:.0f} s ({counted}; at {rate:g} samples "
                            f"per second, NDRF_MAX_WORKER_SAMPLES_PER_SECOND), more than {FIRST_ITERATION_SHARE:g} "
                            f"of the job budget of {limits.job_seconds:g} s (NDRF_MAX_JOB_SECONDS); lower {field} or "
                            f"raise the budget")


def check_scene_report(spec: JobSpec, report: dict, limits: Limits) -> None:
    """Caps on what the sandboxed loader read from the scene: sensors and their films (after
    the job's ``render.resolution``), then the estimate of the job's set-up (its meshes, its
    synthetic targets) and first iteration (:func:`check_first_iteration`)."""
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

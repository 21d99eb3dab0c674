"""A job whose first iteration cannot fit its budget is refused at submission (#46), naming the
field to change: ``services/limits.py``'s ``check_first_iteration``, from the films the sandboxed
loader read, the job's spp, views and optimizer, at ``NDRF_MAX_WORKER_SAMPLES_PER_SECOND``
(``python -m bench.first_iteration``). Before, a 1024x1024 job at 4096 spp over 64 views passed
every per-field cap and held a worker for the whole budget. Since, the estimate runs to the first
iteration's end: it adds the warm-up training of the field methods (``TRAINING_SAMPLE_COST``
samples per incident sample), whose 100,000 steps of 65,536 incident samples passed before, and
the set-up (``tests/unit/test_setup_estimate.py``)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.limits import (
    FIRST_ITERATION_SHARE,
    TRAINING_SAMPLE_COST,
    check_limits,
    check_scene_report,
    first_iteration_samples,
)
from services.settings import Limits

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
DEMO = json.loads((EXAMPLES / "demo.json").read_text())
#: Uploaded targets: nothing rendered at set-up, the first iteration's cost alone.
IMAGES = {"images": [{"data": "AAAA"}]}


def _job(**fields) -> JobSpec:
    return JobSpec.model_validate({**DEMO, **fields})


def _imaged(**fields) -> JobSpec:
    return _job(targets=IMAGES, **fields)


def _report(sensors: list, scalars: int = 3, vertices: int = 0, texels: int = 0) -> dict:
    return {"sensors": sensors, "scalars": scalars, "labels": [], "texels": texels, "vertices": vertices}


def _refused(spec: JobSpec, report: dict, limits: Limits | None = None) -> InvalidJob:
    with pytest.raises(InvalidJob) as refused:
        check_scene_report(spec, report, limits or Limits())
    return refused.value


def test_a_first_iteration_over_the_budget_is_refused_naming_the_spp():
    spec = _imaged(render={"resolution": [1024, 1024], "spp": 4096, "gradient_spp": 4096}, views_per_iteration=64)
    error = _refused(spec, _report([[1024, 1024]] * 64))
    assert error.field == "render.spp"
    message = str(error)
    assert "NDRF_MAX_JOB_SECONDS" in message and "NDRF_MAX_WORKER_SAMPLES_PER_SECOND" in message
    assert f"{1024 * 1024 * 64 * 4096:.3g}" in message


def test_the_refusal_is_at_the_share_of_the_budget():
    limits = Limits(job_seconds=100.0, worker_samples_per_second=1000.0)
    most = int(FIRST_ITERATION_SHARE * 100.0 * 1000.0)              # 50,000 samples
    fits = _imaged(render={"resolution": [100, 100], "spp": 5, "gradient_spp": 5})   # 10,000 pixels x 5
    assert first_iteration_samples(fits, [[100, 100]], 3, False) == (10_000, 5, 0)
    check_scene_report(fits, _report([[100, 100]]), limits)         # exactly at the share: accepted
    over = _imaged(render={"resolution": [100, 100], "spp": 7, "gradient_spp": 5})   # x 6
    assert most < 10_000 * 6
    assert _refused(over, _report([[100, 100]]), limits).field == "render.spp"


def test_levenberg_marquardt_s_jacobian_names_the_parameters():
    """12 RGB values: at least 12 forward-mode renders per view, where Adam would render once."""
    limits = Limits(job_seconds=100.0, worker_samples_per_second=1000.0)
    spec = _imaged(optimizer="levenberg-marquardt", render={"resolution": [100, 100], "spp": 4, "gradient_spp": 4})
    assert first_iteration_samples(spec, [[100, 100]], 36, False) == (10_000, 48, 12)
    assert _refused(spec, _report([[100, 100]], scalars=36), limits).field == "parameters"
    check_scene_report(_imaged(optimizer="adam", render=spec.render.model_dump()), _report([[100, 100]], scalars=36),
                       Limits(job_seconds=100.0, worker_samples_per_second=1000.0))


def test_a_film_too_large_even_at_one_sample_names_the_resolution():
    limits = Limits(job_seconds=10.0, worker_samples_per_second=1000.0)
    spec = _imaged(render={"resolution": [200, 200], "spp": 16, "gradient_spp": 16})
    assert _refused(spec, _report([[200, 200]]), limits).field == "render.resolution"


def test_views_count_for_a_texture_or_a_mesh_under_auto():
    """``auto`` renders one view per iteration, every view for a texture or a mesh; a field
    method's candidate and camera-hit query count as Adam's render."""
    spec = _job(render={"resolution": [64, 64], "spp": 2, "gradient_spp": 2})
    assert first_iteration_samples(spec, [[64, 64]] * 6, 3, False)[0] == 64 * 64
    assert first_iteration_samples(spec, [[64, 64]] * 6, 3, True)[0] == 6 * 64 * 64
    assert first_iteration_samples(_job(method="ndrf-lhs"), [[64, 64]] * 6, 3, False) == (64 * 64, 1, 0)


def test_a_field_method_s_warm_up_over_the_budget_is_refused_naming_its_steps():
    """100,000 warm-up steps of 16,384 x 4 incident samples: each under its cap
    (NDRF_MAX_TRAINING_STEPS, NDRF_MAX_TRAINING_POINTS), together days of training before the
    first gradient; a 64x64 film, whose renders are nothing beside it."""
    training = {"warmup_steps": 100_000, "residual_points": 16_384, "incident_samples": 4}
    spec = _job(method="ndrf-lhs", training=training)
    check_limits(spec, Limits())                                    # every per-field cap passes
    error = _refused(spec, _report([[64, 64]]))
    assert error.field == "training.warmup_steps"
    assert f"{100_000 * 16_384 * 4:.3g} incident samples" in str(error) and "NDRF_MAX_JOB_SECONDS" in str(error)
    # the same job under prb trains nothing
    check_scene_report(_job(method="prb", training=training), _report([[64, 64]]), Limits())


def test_a_warm_up_of_large_batches_names_the_residual_points():
    """The default 400 steps of 4 times the default batch: the batch is what is large."""
    limits = Limits(job_seconds=100.0, worker_samples_per_second=1000.0)
    spec = _imaged(method="radiance-cache", render={"resolution": [8, 8]},
                   training={"warmup_steps": 400, "residual_points": 16_384, "incident_samples": 4})
    most = FIRST_ITERATION_SHARE * 100.0 * 1000.0 / TRAINING_SAMPLE_COST     # incident samples that fit
    assert most < 400 * 16_384 * 4
    assert _refused(spec, _report([[8, 8]]), limits).field == "training.residual_points"
    small = _imaged(method="radiance-cache", render={"resolution": [8, 8]},
                    training={"warmup_steps": 1, "residual_points": 1024, "incident_samples": 4})
    check_scene_report(small, _report([[8, 8]]), limits)               # 4,096 x 5 / 1000 = 20 s: accepted


def test_a_warm_start_s_top_up_counts_instead_of_the_warm_up():
    training = {"warmup_steps": 100_000, "residual_points": 16_384, "incident_samples": 4}
    topped = _job(method="ndrf-rhs", training=training, warm_start={"job": "earlier", "top_up_steps": 100})
    check_scene_report(topped, _report([[64, 64]]), Limits())
    quarter = _job(method="ndrf-rhs", training=training, warm_start={"job": "earlier"})    # 25,000 steps
    assert _refused(quarter, _report([[64, 64]])).field == "warm_start.top_up_steps"


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.json") if not p.name.startswith("experiment")))
def test_every_example_fits_the_default_budget(name):
    """Each example's set-up and first iteration, from the report of its scene as loaded (its
    films, scalars, texels and vertices: synthetic targets, renders and warm-up all counted), fit
    a tenth of half the default 6 hours; and its first iteration's renders still do at its largest
    possible report: 64 views of its films (or 1024 x 1024), every scalar of the cap."""
    from schemas.job import PathScene
    from services.solver.optimize.setup import check

    spec = JobSpec.model_validate(json.loads((EXAMPLES / name).read_text()))
    limits = Limits()
    scene_file = EXAMPLES / spec.scene.path if isinstance(spec.scene, PathScene) else None
    check_scene_report(spec, check(spec, scene_file).report(), Limits(job_seconds=0.1 * limits.job_seconds))
    side = spec.render.resolution or (1024, 1024)
    sensors = [list(side)] * limits.sensors
    pixels, per_pixel, _ = first_iteration_samples(spec, sensors, limits.parameters, True)
    assert pixels * per_pixel / limits.worker_samples_per_second < 0.1 * FIRST_ITERATION_SHARE * limits.job_seconds

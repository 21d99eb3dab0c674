"""A job whose first iteration cannot fit its budget is refused at submission (#46), naming the
field to change: ``services/limits.py``'s ``check_first_iteration``, from the films the sandboxed
loader read, the job's spp, views and optimizer, at ``NDRF_MAX_WORKER_SAMPLES_PER_SECOND``
(``python -m bench.first_iteration``). Before, a 1024x1024 job at 4096 spp over 64 views passed
every per-field cap and held a worker for the whole budget."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.limits import FIRST_ITERATION_SHARE, check_scene_report, first_iteration_samples
from services.settings import Limits

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
DEMO = json.loads((EXAMPLES / "demo.json").read_text())


def _job(**fields) -> JobSpec:
    return JobSpec.model_validate({**DEMO, **fields})


def _report(sensors: list, scalars: int = 3, vertices: int = 0, texels: int = 0) -> dict:
    return {"sensors": sensors, "scalars": scalars, "labels": [], "texels": texels, "vertices": vertices}


def _refused(spec: JobSpec, report: dict, limits: Limits | None = None) -> InvalidJob:
    with pytest.raises(InvalidJob) as refused:
        check_scene_report(spec, report, limits or Limits())
    return refused.value


def test_a_first_iteration_over_the_budget_is_refused_naming_the_spp():
    spec = _job(render={"resolution": [1024, 1024], "spp": 4096, "gradient_spp": 4096}, views_per_iteration=64)
    error = _refused(spec, _report([[1024, 1024]] * 64))
    assert error.field == "render.spp"
    message = str(error)
    assert "NDRF_MAX_JOB_SECONDS" in message and "NDRF_MAX_WORKER_SAMPLES_PER_SECOND" in message
    assert f"{1024 * 1024 * 64 * 4096:.3g}" in message


def test_the_refusal_is_at_the_share_of_the_budget():
    limits = Limits(job_seconds=100.0, worker_samples_per_second=1000.0)
    most = int(FIRST_ITERATION_SHARE * 100.0 * 1000.0)              # 50,000 samples
    fits = _job(render={"resolution": [100, 100], "spp": 5, "gradient_spp": 5})   # 10,000 pixels x 5
    assert first_iteration_samples(fits, [[100, 100]], 3, False) == (10_000, 5, 0)
    check_scene_report(fits, _report([[100, 100]]), limits)         # exactly at the share: accepted
    over = _job(render={"resolution": [100, 100], "spp": 7, "gradient_spp": 5})   # x 6
    assert most < 10_000 * 6
    assert _refused(over, _report([[100, 100]]), limits).field == "render.spp"


def test_levenberg_marquardt_s_jacobian_names_the_parameters():
    """12 RGB values: at least 12 forward-mode renders per view, where Adam would render once."""
    limits = Limits(job_seconds=100.0, worker_samples_per_second=1000.0)
    spec = _job(optimizer="levenberg-marquardt", render={"resolution": [100, 100], "spp": 4, "gradient_spp": 4})
    assert first_iteration_samples(spec, [[100, 100]], 36, False) == (10_000, 48, 12)
    assert _refused(spec, _report([[100, 100]], scalars=36), limits).field == "parameters"
    check_scene_report(_job(optimizer="adam", render=spec.render.model_dump()), _report([[100, 100]], scalars=36),
                       Limits(job_seconds=100.0, worker_samples_per_second=1000.0))


def test_a_film_too_large_even_at_one_sample_names_the_resolution():
    limits = Limits(job_seconds=10.0, worker_samples_per_second=1000.0)
    spec = _job(render={"resolution": [200, 200], "spp": 16, "gradient_spp": 16})
    assert _refused(spec, _report([[200, 200]]), limits).field == "render.resolution"


def test_views_count_for_a_texture_or_a_mesh_under_auto():
    """``auto`` renders one view per iteration, every view for a texture or a mesh."""
    spec = _job(render={"resolution": [64, 64], "spp": 2, "gradient_spp": 2})
    assert first_iteration_samples(spec, [[64, 64]] * 6, 3, False)[0] == 64 * 64
    assert first_iteration_samples(spec, [[64, 64]] * 6, 3, True)[0] == 6 * 64 * 64
    assert first_iteration_samples(_job(method="ndrf-lhs"), [[64, 64]] * 6, 3, False) == (0, 0, 0)


@pytest.mark.parametrize("name", sorted(p.name for p in EXAMPLES.glob("*.json") if not p.name.startswith("experiment")))
def test_every_example_fits_the_default_budget(name):
    """The examples at their largest possible report: 64 views of their films (or 1024 x 1024),
    every scalar of the cap: each one's first iteration far under half of 6 hours."""
    spec = JobSpec.model_validate(json.loads((EXAMPLES / name).read_text()))
    side = spec.render.resolution or (1024, 1024)
    limits = Limits()
    report = _report([list(side)] * limits.sensors, scalars=limits.parameters)
    pixels, per_pixel, _ = first_iteration_samples(spec, report["sensors"], limits.parameters, True)
    assert pixels * per_pixel / limits.worker_samples_per_second < 0.1 * FIRST_ITERATION_SHARE * limits.job_seconds
    check_scene_report(spec, report, limits)

"""A job whose set-up cannot fit its budget is refused at submission (#46), naming the field to
change: ``services/limits.py``'s ``check_first_iteration``, from the vertices the sandboxed loader
counted and the films its synthetic targets are rendered at. Before, a 399,202-vertex shape job
was accepted and held a worker with no iteration; and so was a job whose synthetic targets (every
sensor's film at ``targets.synthetic.spp``, ``TARGET_SAMPLE_COST`` samples each) took hours before
its first iteration: 8 views of 1024 x 1024 at 4096 spp."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.limits import (
    FIRST_ITERATION_SHARE,
    SETUP_SECONDS_PER_VERTEX,
    TARGET_SAMPLE_COST,
    check_limits,
    check_scene_report,
)
from services.settings import Limits

SHAPE = {"scene": {"builtin": "shape-sphere"}, "parameters": [{"key": "sphere.vertex_positions"}],
         "targets": {"synthetic": {"values": {}, "meshes": {"sphere": {"scale": [1.1, 1.0, 1.0]}}}},
         "iterations": 2}
DEMO = json.loads((Path(__file__).resolve().parents[2] / "examples" / "demo.json").read_text())


def _report(vertices: int) -> dict:
    return {"sensors": [[16, 16]], "scalars": 3 * vertices, "labels": [], "texels": 0, "vertices": vertices}


def _views(sensors: list, scalars: int = 3) -> dict:
    return {"sensors": sensors, "scalars": scalars, "labels": [], "texels": 0, "vertices": 0}


def _targets(spp: int, side: int = 1024) -> JobSpec:
    return JobSpec.model_validate({**DEMO, "render": {"resolution": [side, side]},
                                   "targets": {"synthetic": {**DEMO["targets"]["synthetic"], "spp": spp}}})


def test_a_mesh_whose_set_up_cannot_fit_the_budget_is_refused_naming_the_field():
    limits = Limits(job_seconds=60.0)
    most = int(FIRST_ITERATION_SHARE * 60.0 / SETUP_SECONDS_PER_VERTEX)     # 300,000 vertices
    # fits: accepted (1,000 vertices, 0.1 s, leave room for the targets' and the renders' 0.07 s)
    check_scene_report(JobSpec.model_validate(SHAPE), _report(most - 1000), limits)
    with pytest.raises(InvalidJob) as refused:
        check_scene_report(JobSpec.model_validate(SHAPE), _report(most + 1000), limits)
    assert refused.value.field == "parameters"
    assert "sphere.vertex_positions" in str(refused.value) and "NDRF_MAX_JOB_SECONDS" in str(refused.value)


def test_the_default_budget_takes_every_mesh_under_the_vertex_cap():
    """4 Mi vertices (the mesh cap) set up in about 7 minutes at the measured rate: under half of
    the 6-hour default budget."""
    check_scene_report(JobSpec.model_validate(SHAPE), _report(4 << 20), Limits())


def test_synthetic_targets_over_the_budget_are_refused_naming_their_spp():
    """8 views of 1024 x 1024 at 4096 spp: 3.4e10 samples before the first iteration, each field
    under its cap."""
    spec, report = _targets(4096), _views([[1024, 1024]] * 8)
    check_limits(spec, Limits())                                        # every per-field cap passes
    with pytest.raises(InvalidJob) as refused:
        check_scene_report(spec, report, Limits())
    assert refused.value.field == "targets.synthetic.spp"
    message = str(refused.value)
    assert f"{8 * 1024 * 1024 * 4096:.3g}" in message and "NDRF_MAX_JOB_SECONDS" in message
    # a quarter of the spp fits: 8.6e9 samples at TARGET_SAMPLE_COST, under half of 6 hours
    assert 8 * 1024 * 1024 * 1024 * TARGET_SAMPLE_COST / Limits().worker_samples_per_second < 3 * 3600
    check_scene_report(_targets(1024), report, Limits())


def test_targets_too_large_even_at_one_sample_name_the_resolution():
    """Half of a 120 s budget at 1000 samples per second: 60 s. Two 256 x 256 films take 65 s
    at 1 spp (and the first iteration's render 65 s more); two 128 x 128 ones 16 s at 1 spp, 1049 s
    at 64."""
    limits = Limits(job_seconds=120.0, worker_samples_per_second=1000.0)
    with pytest.raises(InvalidJob) as refused:
        check_scene_report(_targets(64, side=256), _views([[256, 256]] * 2), limits)
    assert refused.value.field == "render.resolution"
    with pytest.raises(InvalidJob) as refused:
        check_scene_report(_targets(64, side=128), _views([[128, 128]] * 2), limits)
    assert refused.value.field == "targets.synthetic.spp"

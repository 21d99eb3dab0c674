"""A job whose set-up alone cannot fit its budget is refused at submission (#46), naming the
field to change: ``services/limits.py``'s ``check_setup``, from the vertices the sandboxed loader
counted. Before, a 399,202-vertex shape job was accepted and held a worker with no iteration."""

from __future__ import annotations

import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.limits import SETUP_SECONDS_PER_VERTEX, SETUP_SHARE, check_scene_report
from services.settings import Limits

SHAPE = {"scene": {"builtin": "shape-sphere"}, "parameters": [{"key": "sphere.vertex_positions"}],
         "targets": {"synthetic": {"values": {}, "meshes": {"sphere": {"scale": [1.1, 1.0, 1.0]}}}},
         "iterations": 2}


def _report(vertices: int) -> dict:
    return {"sensors": [[16, 16]], "scalars": 3 * vertices, "labels": [], "texels": 0, "vertices": vertices}


def test_a_mesh_whose_set_up_cannot_fit_the_budget_is_refused_naming_the_field():
    limits = Limits(job_seconds=60.0)
    most = int(SETUP_SHARE * 60.0 / SETUP_SECONDS_PER_VERTEX)              # 300,000 vertices
    check_scene_report(JobSpec.model_validate(SHAPE), _report(most), limits)  # fits: accepted
    with pytest.raises(InvalidJob) as refused:
        check_scene_report(JobSpec.model_validate(SHAPE), _report(most + 1000), limits)
    assert refused.value.field == "parameters"
    assert "sphere.vertex_positions" in str(refused.value) and "NDRF_MAX_JOB_SECONDS" in str(refused.value)


def test_the_default_budget_takes_every_mesh_under_the_vertex_cap():
    """4 Mi vertices (the mesh cap) set up in about 7 minutes at the measured rate: under half of
    the 6-hour default budget."""
    check_scene_report(JobSpec.model_validate(SHAPE), _report(4 << 20), Limits())

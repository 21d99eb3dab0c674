"""Every file in ``examples/`` is a job or an experiment the schemas accept, as ``ndrf run`` and
``ndrf experiment`` read them (a renamed or tightened field would otherwise break an example
that only the docs run). Failed on ``shape-remesh.json`` with ``remesh_at`` [40] (not an
iteration of a 40-iteration run)."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas.experiments import ExperimentSpec
from schemas.job import JobSpec

EXAMPLES = sorted((Path(__file__).resolve().parents[2] / "examples").glob("*.json"))


def test_there_are_examples():
    assert len(EXAMPLES) >= 10


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_an_example_validates(path: Path):
    data = json.loads(path.read_text())
    model = ExperimentSpec if path.name.startswith("experiment-") else JobSpec
    model.model_validate(data)

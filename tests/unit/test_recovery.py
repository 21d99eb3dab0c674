"""Inverse rendering recovers parameters (slow tier; the numbers of the jobs issue).

The jobs are the README's own example files, so the README's claims are what is tested:

* ``examples/demo.json`` (Cornell box, the default recipe): the red wall albedo from 0.2 grey to
  within 0.02 per channel.
* ``examples/hidden-object.json`` (the paper's Fig. 5): ``ndrf-rhs`` recovers the albedo of a
  sphere the camera never sees to within 0.05 per channel; ``radiance-cache`` and ``direct`` see a
  zero gradient and do not move it at all.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from harness.cluster import ROOT

pytestmark = pytest.mark.slow

EXAMPLES = ROOT / "examples"


def _example(name, **overrides):
    job = json.loads((EXAMPLES / name).read_text())
    job.update(images_every=10, **overrides)
    return job


def _run(job, folder):
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    summary = run_local(JobSpec.model_validate(job), folder)
    assert summary["status"] == "succeeded", summary["error"]
    return np.array(summary["estimate"]), np.array(summary["target_values"])


def test_demo_recovers_the_red_wall(mi, tmp_path):
    final, target = _run(_example("demo.json"), tmp_path)
    print("demo (cornell-box, default recipe) final", final.round(4))
    assert np.all(np.abs(final - target) < 0.02)


def test_hidden_object_albedo_is_recovered_only_by_ndrf(mi, tmp_path):
    final, target = _run(_example("hidden-object.json"), tmp_path / "ndrf-rhs")
    print("hidden-object ndrf-rhs final", final.round(4))
    assert np.all(np.abs(final - target) < 0.05)
    for method in ("radiance-cache", "direct"):
        job = _example("hidden-object.json", method=method, iterations=8)
        job["training"] = dict(job["training"], warmup_steps=20)   # L_phi's quality is beside the point
        stuck, _ = _run(job, tmp_path / method)
        print(f"hidden-object {method} final", stuck)
        np.testing.assert_allclose(stuck, 0.2, rtol=0, atol=1e-6)   # no gradient, no motion (float32 round trip)

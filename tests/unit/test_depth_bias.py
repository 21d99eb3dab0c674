"""No silent depth bias: photographs of a bright closed room lead to its true albedo.

The closed room of ``hidden-object`` at 32x32 with walls of albedo 0.95: light bounces tens of
times, and a path tracer truncated at depth 16 misses a large part of it. The targets are
"photographs": rendered by the test with every bounce (unbounded paths, Russian roulette, 1024
spp) and uploaded as images, so the product cannot know how they were made. The default job
recovers the walls within 0.01. The same job with ``render.max_depth`` 16 (the depth the product
used to pick, measured at the initial 0.5 grey) ends biased towards brighter walls, which is
what this test exists to catch (and why the plan warns about a finite depth)."""

from __future__ import annotations

import base64
import io

import numpy as np
import pytest

TRUTH = 0.95


def _photograph_job(mi) -> dict:
    from services.solver.estimators.problem import Problem
    from services.solver.estimators.render import UNBIASED, render
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="hidden-object", resolution=(32, 32))
    params = ParameterSet(scene.params, ["walls.reflectance.value"])
    params.assign(np.full(3, TRUTH))
    photo = render(Problem(scene, params), spp=1024, seed=77, depth=UNBIASED)
    buffer = io.BytesIO()
    np.save(buffer, photo)
    return {"scene": {"builtin": "hidden-object"},
            "parameters": [{"key": "walls.reflectance.value", "init": [0.5, 0.5, 0.5]}],
            "targets": {"images": [{"sensor": 0, "data": base64.b64encode(buffer.getvalue()).decode()}]},
            "render": {"resolution": [32, 32]}, "iterations": 60, "seed": 1}


@pytest.mark.slow
def test_photographs_of_a_bright_closed_room_give_its_true_albedo(mi, tmp_path):
    from tests.support.jobs import run_job as _run

    job = _photograph_job(mi)
    unbiased = _run(job, tmp_path / "default")
    assert unbiased["status"] == "succeeded", unbiased
    walls = np.asarray(unbiased["estimate"])
    assert np.max(np.abs(walls - TRUTH)) < 0.01, walls

    truncated = _run({**job, "render": {"resolution": [32, 32], "max_depth": 16}}, tmp_path / "depth-16")
    assert truncated["status"] == "succeeded", truncated
    assert np.min(np.asarray(truncated["estimate"]) - TRUTH) > 0.01, truncated["estimate"]   # brighter to make up

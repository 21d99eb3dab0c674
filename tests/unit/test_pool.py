"""The residual pool (services/solver/training/pool.py): pooled batches are the batches fresh sampling
draws with the same seeds, stay exact after a parameter step when sampling does not depend on the
parameter, and unbiased (equal in expectation) when it does; batches are redrawn on schedule and
re-evaluated only when the parameters changed."""

from __future__ import annotations

import numpy as np
import pytest
import torch


def _problem(mi, scene_dict, keys):
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(mitsuba_dict=scene_dict)
    return Problem(scene, ParameterSet(scene.params, keys))


def _rough_plane(alpha):
    from tests.support.scenes import sky_plane

    d = sky_plane()
    d["plane-bsdf"] = {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": alpha}
    return d


def test_a_pooled_batch_is_the_fresh_batch_of_its_seed_before_and_after_a_parameter_step(mi):
    from services.solver.seeds import derive_seed
    from services.solver.training.pool import ResidualPool
    from services.solver.training.residuals import draw_batch
    from tests.support.scenes import sky_plane

    problem = _problem(mi, sky_plane([0.2, 0.5, 0.8]), ["plane-bsdf.reflectance.value"])
    pool = ResidualPool(problem, 256, 4, chunks=2, reuse=3, derivatives=True, fields=[], seed=5)
    for step in (0, 1, 2, 5):           # steps 2 and 4 reuse the batch of step 0, step 5 the one of step 1
        batch = pool.batch(step)
        drawn_at = pool.batch_id(step)[1]
        fresh = draw_batch(problem, 256, 4, derive_seed(5, "train", drawn_at, 0), True)
        for name in ("emitted", "throughput", "d_emitted", "d_throughput"):
            assert torch.allclose(getattr(batch, name), getattr(fresh, name), atol=1e-6), (step, name)
    assert pool.draws == 2 and pool.evaluations == 2
    problem.parameters.assign(np.array([0.6, 0.1, 0.3]))      # cosine sampling does not depend on the albedo
    batch = pool.batch(6)
    fresh = draw_batch(problem, 256, 4, derive_seed(5, "train", 6, 0), True)
    assert pool.batch_id(6) == (0, 6) and pool.draws == 3      # three uses of slot 0: redrawn
    assert torch.allclose(batch.emitted, fresh.emitted, atol=1e-6)
    assert torch.allclose(pool.batch(7).emitted.mean((0, 1)), torch.tensor([0.6, 0.1, 0.3]), rtol=0.05)
    assert pool.evaluations == 4                               # slot 1 re-evaluated once, for the new albedo
    pool.batch(9)
    assert pool.evaluations == 4                               # same parameters: nothing re-evaluated


def test_geometry_sampled_for_another_roughness_stays_an_unbiased_estimate(mi):
    """Directions sampled from the GGX lobe of roughness 0.4, re-evaluated at 0.15 (the pdf they
    were drawn with stays a valid importance weight), against fresh samples at 0.15: the incident
    integral under a constant sky (the directional albedo) agrees within 4 standard errors."""
    from services.solver.training.residuals import draw_geometry, evaluate_batch

    problem = _problem(mi, _rough_plane(0.4), ["plane-bsdf.alpha.value"])
    old = draw_geometry(problem, 4096, 16, seed=11)
    problem.parameters.assign(np.array([0.15]))
    reused = evaluate_batch(problem, old, derivatives=False).emitted.mean(1)       # (N, 3)
    fresh = evaluate_batch(problem, draw_geometry(problem, 4096, 16, seed=12), derivatives=False).emitted.mean(1)
    for a, b in ((reused, fresh),):
        diff = (a.mean(0) - b.mean(0)).abs()
        se = torch.sqrt(a.var(0) / a.shape[0] + b.var(0) / b.shape[0])
        assert torch.all(diff < 4 * se), (a.mean(0), b.mean(0), se)
    assert float(fresh.mean()) == pytest.approx(float(reused.mean()), rel=0.03)

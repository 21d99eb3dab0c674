"""Cached camera first hits (services/solver/estimators/first_hits.py): the field candidate against a
path tracer, and the per-ray contraction of dz/dy against the per-scalar images.

The scene is the sky-lit plane of tests/scenes.py, whose fields are known exactly (L_r = ρ and
∂L_r/∂ρ = I everywhere on the plane), so the fields here are set, not trained: what is tested is
the candidate's and the gradient's assembly from them. Tolerances: the path tracer at 256 spp
(16x16 pixels) has a relative standard error of the image mean below 0.3%; the candidate must
match it within 1% (image mean) and 5% (per pixel, RMS).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from services.solver.estimators.render import PathDepth

ALBEDO = np.array([0.2, 0.5, 0.8])


def _constant_field(channels, value):
    """A NeuralField that returns ``value`` ``(channels,)`` everywhere (last layer: bias only)."""
    from schemas.solver import FieldConfig
    from services.solver.fields.field import NeuralField

    field = NeuralField(FieldConfig(), channels, [-2, -2, -2], [2, 2, 2])
    last = field.mlp[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.as_tensor(value, dtype=torch.float32))
    return field


def _setup(mi, rfilter="box", spp=4):
    from services.solver.estimators.first_hits import FirstHitCache
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from tests.support.scenes import sky_plane

    d = sky_plane(ALBEDO)
    d["sensor"]["film"]["rfilter"] = {"type": rfilter}
    scene = load_scene(mitsuba_dict=d)
    problem = Problem(scene, ParameterSet(scene.params, ["plane-bsdf.reflectance.value"]))
    # dL_theta of the plane is the identity: scalar c (the albedo's channel c) changes channel c by 1
    identity = problem.layout.pack(torch.eye(3, dtype=torch.float32)).numpy()
    radiance, differential = _constant_field(3, ALBEDO), _constant_field(problem.layout.outputs, identity)
    cache = FirstHitCache(problem, [0], spp, seed=4, fields=[radiance, differential])
    return problem, cache, radiance, differential


def test_the_field_candidate_matches_a_path_tracer(mi):
    from services.solver.estimators.render import render

    problem, cache, radiance, _ = _setup(mi, spp=16)
    candidate = cache.candidate(0, radiance)
    traced = render(problem, spp=256, seed=1, depth=PathDepth(16, None))
    assert candidate.shape == traced.shape == (16, 16, 3)
    assert candidate.mean((0, 1)) == pytest.approx(traced.mean((0, 1)), rel=0.01)
    assert np.sqrt(np.mean((candidate - traced) ** 2)) < 0.05 * np.sqrt(np.mean(traced ** 2))


@pytest.mark.parametrize("rfilter", ["box", "gaussian"])
def test_the_per_ray_contraction_equals_the_contraction_of_the_images(mi, rfilter):
    from services.solver.estimators.methods import contract

    problem, cache, _, differential = _setup(mi, rfilter)
    dz_dy = np.random.default_rng(0).normal(size=(16, 16, 3)).astype(np.float32)
    images = cache.gradient_images(0, differential)
    assert images.shape == (3, 16, 16, 3)
    assert cache.loss_gradient(0, differential, dz_dy) == pytest.approx(contract(images, dz_dy), rel=1e-5, abs=1e-9)


def test_cached_lhs_images_match_fresh_camera_samples(mi):
    """The cached query is the ndrf-lhs estimator (Eq. 11) on fixed samples: on the plane, whose
    derivative is the identity, both give the plane's coverage of each pixel."""
    from services.solver.estimators.methods import Fields, make_method

    problem, cache, radiance, differential = _setup(mi, spp=16)
    cached = cache.gradient_images(0, differential)
    fresh = make_method("ndrf-lhs").gradient_images(problem, Fields(radiance, differential), spp=16, seed=9)
    assert cached.sum((1, 2)) == pytest.approx(fresh.sum((1, 2)), rel=0.02, abs=0.5)


def test_a_job_runs_on_cached_first_hits_with_adaptive_steps(mi, tmp_path):
    """The loop with render.candidate = 'field', render.first_hits = 'cached' and adaptive
    training steps: records as usual, images only on the iterations that write them."""
    import json

    from tests.support.jobs import SMALL_TRAINING, small_job
    from tests.support.jobs import run_job as _run

    job = small_job("ndrf-lhs", iterations=4, images_every=3,
                    render={"spp": 4, "gradient_spp": 2, "resolution": [16, 16], "candidate": "field",
                            "first_hits": "cached"},
                    training=SMALL_TRAINING | {"adaptive_steps": True, "min_warmup_steps": 4, "plateau_window": 4,
                                               "warmup_steps": 12, "steps_per_iteration": 3})
    summary = _run(job, tmp_path / "job")
    tmp_path = tmp_path / "job"
    assert summary["status"] == "succeeded", summary["error"]
    records = [json.loads((tmp_path / "iterations" / f"{k:06d}" / "record.json").read_text()) for k in range(4)]
    assert 4 <= records[0]["training_steps"] <= 12 and all(1 <= r["training_steps"] <= 3 for r in records[1:])
    assert all(np.isfinite(r["dz_dp"]).all() and len(r["dz_dp"]) == 3 for r in records)
    written = [k for k in range(4) if (tmp_path / "iterations" / f"{k:06d}" / "gradients.npy").is_file()]
    assert written == [0, 3]
    assert np.load(tmp_path / "iterations" / "000003" / "gradients.npy").shape == (3, 16, 16, 3)

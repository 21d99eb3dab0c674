"""Accuracy of the gradient methods against ``prb`` (slow tier; the numbers of the core issue).

Cornell box, 64x64, ``red.reflectance.value``: relative L2 error ||g - g_ref|| / ||g_ref|| of the
gradient images (all three scalars) against ``prb`` at 4096 spp (depth 12, no Russian roulette).
Fields trained for ``STEPS`` steps with the default configuration (about 2 minutes here; the
bench reports the time). Tolerances are the issue's targets:

    ndrf-lhs < 0.10, ndrf-rhs < 0.20 (16 spp query), radiance-cache and direct > 0.35,
    off the red wall (indirect gradients only): ndrf-* at least 3x more accurate than radiance-cache.

Hidden object (closed room, the optimized sphere behind the camera): ``direct`` and
``radiance-cache`` give (near) zero dz/dp; ``ndrf-*`` match ``prb`` (2048 spp: dz/dp sums over
all pixels, so its noise is far below the 25% tolerance) in sign and within 25%.
"""

from __future__ import annotations

import numpy as np
import pytest

from services.solver.estimators.render import PathDepth

pytestmark = pytest.mark.slow

STEPS = 300


def _relative(g, ref, where=None):
    if where is not None:
        g, ref = g[:, where], ref[:, where]
    return float(np.linalg.norm(g - ref) / np.linalg.norm(ref))


def _setup(scene_name, key, resolution=(64, 64)):
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin=scene_name, resolution=resolution)
    return Problem(scene, ParameterSet(scene.params, [key]))


def _trained(problem, steps):
    from schemas.solver import TrainingConfig
    from services.solver.training.trainer import FieldTrainer

    trainer = FieldTrainer(problem, TrainingConfig(), radiance=True, differential=True, seed=0)
    trainer.train(steps)
    return trainer.queried()  # what the methods read in a job: the weight averages


@pytest.fixture(scope="module")
def cornell(mi):
    from services.solver.estimators.methods import Fields, make_method

    problem = _setup("cornell-box", "red.reflectance.value")
    reference = make_method("prb", None, PathDepth(12, None)).gradient_images(problem, Fields(), spp=4096, seed=12345)
    fields = _trained(problem, STEPS)
    images = {name: make_method(name).gradient_images(problem, Fields() if name == "direct" else fields, spp=16, seed=1)
              for name in ("ndrf-lhs", "ndrf-rhs", "radiance-cache", "direct")}
    return reference, images


def test_cornell_box_errors_against_prb(cornell):
    reference, images = cornell
    errors = {name: _relative(g, reference) for name, g in images.items()}
    print("relative L2 errors:", {k: round(v, 4) for k, v in errors.items()})
    assert errors["ndrf-lhs"] < 0.10
    assert errors["ndrf-rhs"] < 0.20
    assert errors["radiance-cache"] > 0.35
    assert errors["direct"] > 0.35


def test_cornell_box_indirect_gradients_off_the_red_wall(cornell):
    reference, images = cornell
    off_wall = np.abs(images["direct"]).sum(axis=(0, 3)) == 0      # pixels the red wall's BSDF never touches
    assert off_wall.mean() > 0.5
    errors = {name: _relative(g, reference, off_wall) for name, g in images.items()}
    print("off-wall relative L2 errors:", {k: round(v, 4) for k, v in errors.items()})
    assert errors["radiance-cache"] > 3 * errors["ndrf-lhs"]
    assert errors["radiance-cache"] > 3 * errors["ndrf-rhs"]


def test_hidden_object_gradient_only_ndrf_sees(mi):
    from services.solver.estimators.losses import image_loss
    from services.solver.estimators.methods import Fields, make_method
    from services.solver.estimators.render import render

    problem = _setup("hidden-object", "hidden.reflectance.value")
    params = problem.parameters
    target = render(problem, spp=256, seed=3, depth=PathDepth(12, None))  # the scene's own albedo (0.8, 0.35, 0.1)
    params.assign(np.full(3, 0.2))
    candidate = render(problem, spp=256, seed=4, depth=PathDepth(12, None))
    _, dz_dy = image_loss("l2", candidate, target)

    reference = make_method("prb", None, PathDepth(12, None)).loss_gradient(problem, Fields(), dz_dy, spp=2048, seed=5)
    fields = _trained(problem, 250)
    dz_dp = {name: make_method(name).loss_gradient(problem, Fields() if name == "direct" else fields, dz_dy,
                                                   spp=64, seed=6)
             for name in ("ndrf-lhs", "ndrf-rhs", "radiance-cache", "direct")}
    print("prb dz/dp", reference, {k: v.tolist() for k, v in dz_dp.items()})
    scale = np.abs(reference).max()
    for name in ("direct", "radiance-cache"):
        assert np.abs(dz_dp[name]).max() < 1e-3 * scale
    for name in ("ndrf-lhs", "ndrf-rhs"):
        significant = np.abs(reference) > 0.05 * scale            # channels with a real gradient
        assert np.all(np.sign(dz_dp[name][significant]) == np.sign(reference[significant]))
        assert np.all(np.abs(dz_dp[name] - reference)[significant] <= 0.25 * np.abs(reference[significant]))

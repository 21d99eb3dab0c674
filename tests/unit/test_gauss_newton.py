"""Gauss-Newton steps (``services/solver/optimize/optimizers/gauss_newton.py``): exact on a linear model,
inside the trust region and the bounds, and in the loop for every kind of method.

The linear model ``y = Σ_i p_i J_i`` stands for a scene whose image is linear in its scalars;
``J`` has two nearly collinear columns, as a hidden sphere's albedo and the walls' have in a
bright closed room (``bench/regime.py``)."""

from __future__ import annotations

import numpy as np
import pytest

from services.solver.optimize.optimizers.adam import Adam
from services.solver.optimize.optimizers.gauss_newton import gauss_newton_hessian, gauss_newton_step
from tests.support.linear import coupled_model, gradient


def test_the_hessian_is_two_over_n_jtj():
    images, _, _ = coupled_model()
    jac = images.reshape(3, -1).astype(np.float64)
    np.testing.assert_allclose(gauss_newton_hessian(images), 2 / jac.shape[1] * jac @ jac.T, rtol=1e-12)
    with pytest.raises(ValueError, match=r"\(P, H, W, C\)"):
        gauss_newton_hessian(images[0])


def test_an_undamped_step_lands_on_the_minimum_of_a_linear_model():
    """Scaled consistently with image_loss's gradient: one full step is exact (float32 images)."""
    images, truth, target = coupled_model()
    p0 = np.array([0.5, 0.5, 0.5])
    p1 = gauss_newton_step(p0, gradient(images, p0, target), gauss_newton_hessian(images),
                           np.zeros(3), np.ones(3), lr=10.0, damping=0.0)
    np.testing.assert_allclose(p1, truth, atol=1e-4)


def test_in_a_coupled_valley_gauss_newton_arrives_where_adam_crawls():
    """Same trust region (lr 0.05 per scalar and iteration) and 60 noiseless iterations. H's
    curvatures span 4.6 to 9.5e-5 here: a damping of 1e-2 would stall Gauss-Newton as well (it
    ends 0.30 away), 1e-3 ends 0.034 away, 1e-4 (the default) and below arrive."""
    images, truth, target = coupled_model()
    lower, upper = np.zeros(3), np.ones(3)
    p_gn = p_adam = np.array([0.5, 0.5, 0.5])
    adam = Adam(3, 0.05, 0.8, 0.99)
    hessian = gauss_newton_hessian(images)
    for _ in range(60):
        p_gn = gauss_newton_step(p_gn, gradient(images, p_gn, target), hessian, lower, upper, lr=0.05, damping=1e-4)
        p_adam = adam.step(p_adam, gradient(images, p_adam, target), lower, upper)
    assert np.max(np.abs(p_gn - truth)) < 1e-3, p_gn
    assert np.max(np.abs(p_adam - truth)) > 0.1, p_adam        # why the option exists


def test_steps_stay_in_the_trust_region_and_the_bounds():
    images, _, target = coupled_model()
    p0 = np.array([0.02, 0.98, 0.5])
    p1 = gauss_newton_step(p0, gradient(images, p0, target), gauss_newton_hessian(images),
                           np.zeros(3), np.ones(3), lr=0.03, damping=0.01)
    assert np.max(np.abs(p1 - p0)) <= 0.03 + 1e-12
    p2 = gauss_newton_step(p0, gradient(images, p0, target), gauss_newton_hessian(images),
                           np.array([0.0, 0.97, 0.0]), np.ones(3), lr=10.0, damping=0.01)
    assert p2[1] >= 0.97 and np.all(p2 <= 1.0)


def test_a_scalar_no_pixel_depends_on_stays_where_it_is():
    images, _, target = coupled_model()
    images = np.concatenate([images, np.zeros((1, 8, 8, 3), np.float32)])   # a dropped scalar
    p0 = np.array([0.5, 0.5, 0.5, 0.3])
    p1 = gauss_newton_step(p0, gradient(images, p0, target), gauss_newton_hessian(images),
                           np.zeros(4), np.ones(4), lr=0.05, damping=0.01)
    assert np.all(np.isfinite(p1)) and p1[3] == 0.3 and np.any(p1[:3] != p0[:3])


def test_non_finite_input_is_refused():
    with pytest.raises(FloatingPointError):
        gauss_newton_step(np.zeros(2), np.array([np.nan, 0.0]), np.eye(2), np.zeros(2), np.ones(2), lr=0.1, damping=0)


def test_gauss_newton_is_l2_only():
    from pydantic import ValidationError

    from schemas.job import JobSpec
    from tests.support.jobs import small_job

    with pytest.raises(ValidationError, match="l2"):
        JobSpec.model_validate(small_job("prb", optimizer="gauss-newton", loss="l1"))
    with pytest.raises(ValidationError, match="hessian 'cross' is a second-order optimizer's"):
        JobSpec.model_validate(small_job("prb", optimizer="adam", hessian="cross"))


@pytest.mark.parametrize(("method", "hessian"), [("prb", "product"), ("ndrf-lhs", "product"), ("prb", "cross")])
def test_the_loop_runs_gauss_newton_steps_towards_the_target(mi, tmp_path, method, hessian):
    from tests.support.jobs import run_job as _run
    from tests.support.jobs import small_job

    summary = _run(small_job(method, iterations=6, learning_rate=0.1, final_learning_rate_ratio=1.0,
                             optimizer="gauss-newton", hessian=hessian), tmp_path)
    assert summary["status"] == "succeeded", summary
    first, last, target = map(np.asarray, (summary["init"], summary["estimate"], summary["target_values"]))
    assert last[0] > first[0] + 0.15         # red rises towards 0.57 (6 steps of at most 0.1 each)
    assert last[1] < first[1] and last[2] < first[2]
    assert np.max(np.abs(last - target)) < np.max(np.abs(first - target)) - 0.1


def test_the_cross_hessian_removes_the_variance_the_product_adds():
    """Monte Carlo noise of variance σ² per value adds 2σ² to the diagonal of (2/n) JᵀJ in
    expectation; the cross product of two independent estimates has none. Averaged over 200 draws
    (σ = 0.3: bias 0.18), the product's diagonal is 0.18 too high and the cross product's is
    within 0.02 (about 4 standard errors) of the noiseless Hessian."""
    images, _, _ = coupled_model()
    exact = gauss_newton_hessian(images)
    rng = np.random.default_rng(1)
    product, cross = np.zeros_like(exact), np.zeros_like(exact)
    for _ in range(200):
        a, b = (images + rng.normal(0.0, 0.3, images.shape) for _ in range(2))
        product += gauss_newton_hessian(a) / 200
        cross += gauss_newton_hessian(a, b) / 200
    np.testing.assert_allclose(np.diag(product - exact), 2 * 0.3**2, atol=0.02)
    assert np.max(np.abs(cross - exact)) < 0.02
    with pytest.raises(ValueError, match="differ in shape"):
        gauss_newton_hessian(images, images[:2])


def test_an_indefinite_hessian_still_gives_a_bounded_descent_step():
    """A noisy cross product can have a negative eigenvalue: the step uses it with that
    eigenvalue raised (not a step uphill, not a solve of a singular system)."""
    h = np.array([[1.0, 0.0], [0.0, -0.2]])
    g = np.array([0.3, -0.4])
    p0 = np.array([0.5, 0.5])
    p1 = gauss_newton_step(p0, g, h, np.zeros(2), np.ones(2), lr=0.05, damping=0.0)
    delta = p1 - p0
    assert np.all(np.isfinite(p1)) and np.max(np.abs(delta)) <= 0.05 + 1e-12
    assert float(g @ delta) < 0                                          # downhill


def test_the_successive_curvature_of_a_batch_of_every_view_is_the_sum_over_them():
    """Four views whose Jacobians are 1, 2, 3 and 4 times one ``J`` (a ball seen near and far), each
    iteration's batch every view, one noisy Jacobian measured per iteration (``σ = 0.3``): the mean
    of 200 iterations' ``H`` is ``Σ_s (2/n) J_sᵀJ_s`` = 30 times the one view's, within 3%. (Its
    first view alone, measured at every iteration, had stood for all four: 4 times it, plus the
    product's noise.)"""
    from services.solver.optimize.optimizers.curvature import Curvature, jacobian_matrix

    images, _, _ = coupled_model()
    j = jacobian_matrix(images)
    exact = sum(gauss_newton_hessian(images * (s + 1)) for s in range(4))
    curvature, rng, at = Curvature("successive", views=4), np.random.default_rng(2), np.zeros(j.shape[0])
    mean = np.zeros_like(exact)
    for k in range(240):
        measured, draws = curvature.wanted(k, [0, 1, 2, 3])
        assert draws == 1 and len(measured) == 1
        h = curvature.update({s: [j * (s + 1) + rng.normal(0.0, 0.3, j.shape)] for s in measured}, at, lr=1.0)
        mean += h / 200 if k >= 40 else 0.0
    np.testing.assert_allclose(np.diag(mean), np.diag(exact), rtol=0.03)

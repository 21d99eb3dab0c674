"""The coarse-to-fine loss of geometry jobs (services/solver/optimize/blur.py,
services/solver/estimators/losses.py BlurredLoss): its gradient against finite differences, its
Jacobian against the images it compares, and the schedule a job resolves to."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.job import JobSpec
from services.solver.estimators.losses import BlurredLoss, ImageLoss, blur, gaussian_matrix
from services.solver.optimize.blur import BlurSchedule, resolve_blur


def test_the_blur_is_its_own_adjoint_and_keeps_the_interior_mean():
    g = gaussian_matrix(20, 2.5)
    np.testing.assert_allclose(g, g.T)                        # so dz/dy = G (dz/d(Gy))
    np.testing.assert_allclose(g[10].sum(), 1.0)              # an interior row is a mean
    np.testing.assert_array_equal(gaussian_matrix(5, 0.0), np.eye(5))
    with pytest.raises(ValueError, match="sigma"):
        gaussian_matrix(5, -1.0)


@pytest.mark.parametrize("kind", ["l2", "l1"])
def test_the_blurred_loss_gradient_matches_finite_differences(kind):
    """Tolerance: central differences of step 1e-4 on a float64 loss; 1e-4 relative (l1's kink
    is never crossed: no residual is within the step of 0 at these random images)."""
    rng = np.random.default_rng(3)
    target, image = rng.random((12, 10, 3)), rng.random((12, 10, 3))
    loss = BlurredLoss(ImageLoss(kind, target), 1.7)
    z, dz_dy = loss(image)
    assert z == pytest.approx(ImageLoss(kind, blur(target, 1.7))(blur(image, 1.7))[0], rel=1e-5)
    for index in [(0, 0, 0), (5, 4, 1), (11, 9, 2), (6, 0, 1)]:
        step = np.zeros_like(image)
        step[index] = 1e-4
        numeric = (loss(image + step)[0] - loss(image - step)[0]) / 2e-4
        assert dz_dy[index] == pytest.approx(numeric, rel=1e-4, abs=1e-9), index


def test_the_jacobian_is_that_of_the_compared_images():
    """``G J`` is the derivative of ``G y(p)`` for a linear image ``y(p) = y0 + J p``."""
    rng = np.random.default_rng(4)
    y0, jac, p = rng.random((8, 9, 3)), rng.random((2, 8, 9, 3)), np.array([0.3, -0.2])
    loss = BlurredLoss(ImageLoss("l2", y0), 1.2)
    moved = loss.image(y0 + np.tensordot(p, jac, 1)) - loss.image(y0)
    np.testing.assert_allclose(moved, np.tensordot(p, loss.jacobian(jac), 1), atol=1e-12)
    assert ImageLoss("l2", y0).jacobian(jac) is jac


def test_the_schedule_narrows_linearly_then_stays():
    schedule = BlurSchedule(start=4.0, end=1.0, until=6)
    assert [schedule.at(k) for k in (0, 3, 6, 20)] == [4.0, 2.5, 1.0, 1.0]
    assert BlurSchedule(0.0, 0.0, 1).at(0) == 0.0


def _spec(**geometry) -> JobSpec:
    return JobSpec.model_validate({"scene": {"builtin": "pose-block"}, "iterations": 20, "geometry": geometry,
                                   "parameters": [{"key": "block.to_world.translate"}],
                                   "targets": {"synthetic": {"values": {"block.to_world.translate": [0.1, 0, 0]}}}})


def test_a_pose_is_blurred_by_default_and_vertex_positions_are_not():
    decisions = []
    schedule = resolve_blur(_spec(), pose=True, shape=False, film=lambda: (64, 48), decide=lambda *d: decisions.append(d))
    assert schedule == BlurSchedule(start=3.0, end=1.0, until=8) and decisions[0][:2] == ("blur", 3.0)
    assert resolve_blur(_spec(), pose=False, shape=True, film=lambda: (64, 64), decide=lambda *d: None) is None
    assert resolve_blur(_spec(), pose=True, shape=False, film=lambda: (32, 24), decide=lambda *d: None) is None   # too small
    assert resolve_blur(_spec(blur_px=0), pose=True, shape=False, film=lambda: (64, 64), decide=lambda *d: None) is None
    assert resolve_blur(_spec(blur_px=2, blur_end_px=0, blur_share=0.5), pose=False, shape=True, film=lambda: (64, 64),
                        decide=lambda *d: None) == BlurSchedule(2.0, 0.0, 10)
    assert resolve_blur(_spec(), pose=False, shape=False, film=lambda: (64, 64), decide=lambda *d: None) is None

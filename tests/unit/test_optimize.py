"""Pure pieces of the loop: Adam with projection, losses, the learning-rate schedule."""

from __future__ import annotations

import numpy as np
import pytest


def test_adam_first_step_is_lr_times_sign_and_projects_onto_bounds():
    from services.solver.optimize.optimizers.adam import Adam

    adam = Adam(3, lr=0.1)
    p = adam.step(np.array([0.5, 0.5, 0.05]), np.array([2.0, -3.0, 1.0]), np.zeros(3), np.ones(3))
    # first step: m̂ = g, v̂ = g², so the update is lr · sign(g) (up to ε)
    assert p == pytest.approx([0.4, 0.6, 0.0], abs=1e-6)   # third clipped at the lower bound 0


def test_adam_refuses_a_non_finite_gradient():
    from services.solver.optimize.optimizers.adam import Adam

    with pytest.raises(FloatingPointError, match="non-finite"):
        Adam(2, lr=0.1).step(np.zeros(2), np.array([np.nan, 1.0]), np.zeros(2), np.ones(2))
    with pytest.raises(ValueError, match="learning rate"):
        Adam(2, lr=0.0)


def test_losses_and_their_pixel_gradients():
    from services.solver.estimators.losses import image_loss

    rng = np.random.default_rng(0)
    y, t = rng.random((4, 5, 3)), rng.random((4, 5, 3))
    for kind in ("l2", "l1"):
        z, dz = image_loss(kind, y, t)
        h = 1e-6
        bumped = y.copy()
        bumped[1, 2, 0] += h
        numeric = (image_loss(kind, bumped, t)[0] - z) / h
        assert dz[1, 2, 0] == pytest.approx(numeric, rel=1e-3)


def test_learning_rate_decays_geometrically_to_the_final_ratio():
    from services.solver.optimize.recipe import Steps

    steps = Steps(optimizer="adam", learning_rate=0.2, final_learning_rate_ratio=0.01, iterations=11,
                  betas=(0.8, 0.99), damping=0.0, curvature="successive", curvature_every=1, trust_growth=1.5,
                  trust_start=1.0)
    assert steps.learning_rate_at(0) == pytest.approx(0.2)
    assert steps.learning_rate_at(5) == pytest.approx(0.02)
    assert steps.learning_rate_at(10) == pytest.approx(0.002)


@pytest.mark.parametrize("kind", ["l2", "l1"])
def test_the_device_loss_is_the_host_loss_and_counts_what_it_zeroes(mi, kind):
    """``ImageLoss.device`` (what prb uses to stay on the device) and ``ImageLoss.__call__`` (numpy)
    give the same ``z`` and ``dz/dy`` to float32 rounding, and both zero and count NaN pixels."""
    import drjit as dr

    from services.solver.estimators.losses import ImageLoss

    rng = np.random.default_rng(1)
    y, t = rng.random((6, 5, 3)).astype(np.float32), rng.random((6, 5, 3)).astype(np.float32)
    y[2, 3, 1] = np.nan
    counted = []
    loss = ImageLoss(kind, t, lambda where, count: counted.append((where, count)))
    z_host, g_host = loss(y)
    z, g, bad = loss.device(mi.TensorXf(y))
    dr.eval(z, g, bad)
    assert float(np.asarray(z).reshape(-1)[0]) == pytest.approx(z_host, rel=1e-5)
    np.testing.assert_allclose(np.asarray(g), g_host, rtol=1e-5, atol=1e-9)
    assert int(np.asarray(bad).reshape(-1)[0]) == 1 and counted == [(ImageLoss.WHERE, 1)]

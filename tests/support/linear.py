"""A linear stand-in for a scene: ``y = Σ_i p_i J_i``, with two nearly collinear columns of ``J``
as a hidden sphere's albedo and the walls' have in a bright closed room."""

from __future__ import annotations

import numpy as np

from services.solver.estimators.losses import image_loss
from services.solver.estimators.methods.base import contract


def coupled_model(seed=0):
    rng = np.random.default_rng(seed)
    walls = rng.uniform(0.5, 1.5, (8, 8, 3))
    sphere = 0.97 * walls + 0.03 * rng.uniform(0.0, 1.0, (8, 8, 3))      # almost the same image
    light = rng.uniform(0.0, 0.3, (8, 8, 3))
    images = np.stack([walls, sphere, light]).astype(np.float32)        # J = dy/dp, (P, H, W, 3)
    truth = np.array([0.95, 0.2, 0.6])
    return images, truth, np.einsum("phwc,p->hwc", images.astype(np.float64), truth)


def gradient(images, p, target):
    """dz/dp as the loop forms it: the l2 loss of image_loss contracted with dy/dp (Eq. 10)."""
    y = np.einsum("phwc,p->hwc", images.astype(np.float64), p)
    _, dz_dy = image_loss("l2", y.astype(np.float32), target.astype(np.float32))
    return contract(images, dz_dy)

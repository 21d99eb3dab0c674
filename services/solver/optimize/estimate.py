"""What Sec. 5 steps 2-5 give for an iteration's batch of views (:meth:`.run.Run.estimate`
computes them): each view's candidate ``y`` ``(H, W, 3)``,
its loss ``z(y)`` against the target, and ``dz/dp`` ``(P,)`` from the recipe's gradient method
(Eq. 10), summed over the batch and scaled to estimate the sum over every view
(:class:`~services.solver.optimize.views.Batch`); and, for the views the optimizer's curvature
asks for, the Jacobian ``J = dI/dp`` ``(P, H, W, 3)`` (Eq. 3), averaged over pixel blocks into
``(P, n)`` matrices (:func:`~services.solver.optimize.optimizers.curvature.jacobian_matrix`).

When the Jacobian is the method's own, the same samples give the candidate, ``dz/dp`` and ``J``
(``candidate_gradient_and_images``); from another source (the hybrid's ``dL_theta``) it is one
more query with its own seed. A second independent estimate, for the ``cross`` curvature, has its
own seed too.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from services.solver.estimators.problem import Problem
from services.solver.optimize.optimizers.curvature import BLOCK, jacobian_matrix
from services.solver.optimize.recipe import Recipe


@dataclass
class BatchEstimate:
    """What an iteration's batch gave at its parameters (module docstring)."""

    loss: float
    dz_dp: np.ndarray                                   # (P,) float64
    candidates: dict[int, np.ndarray] = field(default_factory=dict)          # view -> (H, W, 3)
    jacobians: dict[int, list[np.ndarray]] = field(default_factory=dict)     # view -> [(P, n) float64, ...]
    unbiased: np.ndarray | None = None                  # (P,) prb's dz/dp of the same views (recipe.bias_every)


#: Methods whose own Jacobian is a per-pixel Monte Carlo estimate (paths, or one bounce, at the
#: gradient's samples per pixel), noisy enough at 1 spp to inflate ``J Jᵀ``.
MONTE_CARLO_JACOBIANS = ("prb", "ndrf-rhs", "radiance-cache", "direct")


def block_of(recipe: Recipe) -> int:
    """Pixels per block side the Jacobian is averaged over: :data:`BLOCK` for a Monte Carlo one
    (:data:`MONTE_CARLO_JACOBIANS`: 1-spp noise, which the curvature ``J Jᵀ`` and the floor
    would add to the signal), 1 for ``dL_theta`` read at the camera hits (smooth already)."""
    return BLOCK if recipe.jacobian == "method" and recipe.method in MONTE_CARLO_JACOBIANS else 1


def jacobian_of(problem: Problem, images: np.ndarray, block: int) -> np.ndarray:
    """``(P, H, W, 3)`` gradient images as a block-averaged ``(P, n)`` matrix, non-finite pixels
    zeroed and counted in the job's metrics (never silently)."""
    bad = ~np.isfinite(images)
    if bad.any():
        problem.count_sanitized("Jacobian pixels (non-finite)", int(bad.sum()))
        images = np.where(bad, 0.0, images).astype(images.dtype)
    return jacobian_matrix(images, block)


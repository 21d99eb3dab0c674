"""Sec. 5 steps 2-5 for an iteration's batch of views: each view's candidate ``y`` ``(H, W, 3)``,
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

from services.solver.estimators.methods import Fields
from services.solver.estimators.problem import Problem
from services.solver.optimize.build import Built
from services.solver.optimize.optimizers.curvature import BLOCK, jacobian_matrix
from services.solver.optimize.recipe import Recipe
from services.solver.optimize.setup import Prepared
from services.solver.optimize.state import RunState
from services.solver.optimize.views import Batch
from services.solver.seeds import derive_seed


@dataclass
class BatchEstimate:
    """What an iteration's batch gave at its parameters (module docstring)."""

    loss: float
    dz_dp: np.ndarray                                   # (P,) float64
    candidates: dict[int, np.ndarray] = field(default_factory=dict)          # view -> (H, W, 3)
    jacobians: dict[int, list[np.ndarray]] = field(default_factory=dict)     # view -> [(P, n) float64, ...]


def block_of(recipe: Recipe) -> int:
    """Pixels per block side the Jacobian is averaged over: :data:`BLOCK` for ``prb``'s own
    (1-spp Monte Carlo noise), 1 for a field's (smooth already)."""
    return BLOCK if recipe.jacobian == "method" and recipe.method == "prb" else 1


def estimate_batch(k: int, prepared: Prepared, recipe: Recipe, built: Built, state: RunState, batch: Batch,
                   fields: Fields) -> BatchEstimate:
    """Iteration ``k``'s :class:`BatchEstimate` at the scene's current parameters."""
    problem, seed0, size = prepared.problem, prepared.spec.seed, state.batch
    measured, draws = built.optimizer.jacobians_wanted(k, batch.sensors)
    block = block_of(recipe)
    out = BatchEstimate(0.0, np.zeros(problem.parameters.n))
    for view in batch.sensors:
        seed = derive_seed(seed0, "iteration", k, view)
        loss = state.loss_of(prepared, view, recipe.blur_at(k))
        images = None
        if view in measured and built.jacobian is None:
            candidate, z, dz_dp, images = built.method.candidate_gradient_and_images(
                problem, fields, loss, spp=size.spp, gradient_spp=size.gradient_spp, seed=seed, depth=recipe.depth,
                sensor=view)
        else:
            candidate, z, dz_dp = built.method.candidate_and_gradient(
                problem, fields, loss, spp=size.spp, gradient_spp=size.gradient_spp, seed=seed, depth=recipe.depth,
                sensor=view)
            if view in measured:
                images = built.jacobian_source.gradient_images(problem, fields, spp=size.gradient_spp,
                                                      seed=derive_seed(seed, "jacobian"), sensor=view)
        out.dz_dp += batch.scale * dz_dp
        out.loss += batch.scale * z
        out.candidates[view] = candidate
        if images is not None:   # the Jacobian of the loss's images (a blurred loss's: G J)
            out.jacobians[view] = [_matrix(problem, loss.jacobian(images), block)]
            if draws > 1:
                other = built.jacobian_source.gradient_images(problem, fields, spp=size.gradient_spp,
                                                     seed=derive_seed(seed, "cross"), sensor=view)
                out.jacobians[view].append(_matrix(problem, loss.jacobian(other), block))
    return out


def _matrix(problem: Problem, images: np.ndarray, block: int) -> np.ndarray:
    """``(P, H, W, 3)`` gradient images as a block-averaged ``(P, n)`` matrix, non-finite pixels
    zeroed and counted in the job's metrics (never silently)."""
    bad = ~np.isfinite(images)
    if bad.any():
        problem.count_sanitized("Jacobian pixels (non-finite)", int(bad.sum()))
        images = np.where(bad, 0.0, images).astype(images.dtype)
    return jacobian_matrix(images, block)


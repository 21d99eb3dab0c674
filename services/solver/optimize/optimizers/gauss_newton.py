"""The damped Gauss-Newton step and the Gauss-Newton optimizer (the curvature ``H`` and its estimates: :mod:`.curvature`).

For the ``l2`` loss ``z = (1/n) Σ (y - t)²`` over the ``n`` values of a view's image, with
``J = dy/dp`` the gradient images of Eq. 3, shape ``(P, H, W, 3)``, the Gauss-Newton model of
the Hessian is ``H = (2/n) JᵀJ`` (summed over views, as the losses are), and the damped step
over the *free* scalars (those not held at a bound by a gradient pushing outwards) is::

    Δ = -(H + λ diag(H) + μ I)⁻¹ ∇z,        ∇z = dz/dp of Eq. 10 (the method's own estimate)

``λ`` (``damping``) is Marquardt's scaled damping; ``μ = 1e-12 · trace(H) / P`` only keeps a
scalar that no pixel depends on (zero row of ``J``, zero gradient) from making ``H`` singular.
:class:`GaussNewton` caps the step at the learning rate (``max |Δ_i| <= lr_k``), a trust region of
the size of Adam's per-coordinate step; :mod:`.levenberg_marquardt` adapts the radius.

Why: when scalars trade against each other in the image (the albedo of a sphere against the
walls' in a bright closed room), the loss is a narrow curved valley. Adam normalises each
coordinate on its own, oscillates across the valley and crawls along it; ``H⁻¹`` takes the
coupling into account. Noise in a Monte Carlo ``J`` adds its variance to ``JᵀJ`` (``E[JᵀJ] =
J̄ᵀJ̄ + Σ``, mostly on the diagonal): it damps the step, most of all along the valley, whose
curvature is the smallest. Two remedies: the images are averaged over ``block x block`` pixel
blocks before the product (the variance term falls by ``block²``, a smooth ``J`` is unchanged),
and ``hessian = "cross"`` uses two independent estimates ``J_a``, ``J_b``: ``H = (1/n) (J_aᵀJ_b +
J_bᵀJ_a)`` has expectation ``(2/n) J̄ᵀJ̄``. It is noisier and may be indefinite; the step then uses
it with its eigenvalues raised to at least ``1e-6`` of the largest.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from services.solver.optimize.optimizers.base import ParameterOptimizer, check_finite
from services.solver.optimize.optimizers.curvature import BLOCK, gauss_newton_hessian, hessian_of, jacobian_matrix

if TYPE_CHECKING:
    from services.solver.optimize.optimizers.curvature import Curvature

__all__ = ["BLOCK", "GaussNewton", "damped_step", "free_scalars", "gauss_newton_hessian", "gauss_newton_step",
           "hessian_of", "jacobian_matrix"]

def _positive(h: np.ndarray, floor: float = 1e-6) -> np.ndarray:
    """``h`` with its eigenvalues raised to at least ``floor`` times the largest (unchanged if
    they all are already)."""
    values, vectors = np.linalg.eigh((h + h.T) / 2)
    top = max(float(values.max()), 1e-300) if values.size else 1.0
    if values.size == 0 or values.min() >= floor * top:
        return h
    return (vectors * np.maximum(values, floor * top)) @ vectors.T


def free_scalars(p: np.ndarray, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    """Scalars a step may move: not at a bound that the descent direction ``-gradient`` points
    out of (``(P,)`` bool)."""
    p, g = np.asarray(p, np.float64), np.asarray(gradient, np.float64)
    return ~(((p <= lower) & (g > 0)) | ((p >= upper) & (g < 0)))


def damped_step(gradient: np.ndarray, hessian: np.ndarray, damping: float, free: np.ndarray | None = None) -> np.ndarray:
    """``Δ`` of the module docstring over the ``free`` scalars (zero for the others)."""
    g = np.asarray(gradient, np.float64)
    h = np.asarray(hessian, np.float64)
    check_finite(g, h)
    if h.shape != (g.size, g.size):
        raise ValueError(f"Hessian of shape {h.shape} for {g.size} scalars")
    if damping < 0:
        raise ValueError(f"damping must be >= 0, got {damping}")
    free = np.ones(g.size, bool) if free is None else np.asarray(free, bool)
    delta = np.zeros(g.size)
    if not free.any():
        return delta
    sub = _positive(h[np.ix_(free, free)])
    mu = 1e-12 * max(float(np.trace(sub)) / max(int(free.sum()), 1), 1e-300)
    system = sub + damping * np.diag(np.diag(sub)) + mu * np.eye(int(free.sum()))
    delta[free] = -np.linalg.solve(system, g[free])
    return delta


def gauss_newton_step(p: np.ndarray, gradient: np.ndarray, hessian: np.ndarray, lower: np.ndarray,
                      upper: np.ndarray, *, lr: float, damping: float) -> np.ndarray:
    """One damped Gauss-Newton step, no scalar moving more than ``lr`` (module docstring); returns
    the new parameters ``(P,)``."""
    if not lr > 0:
        raise ValueError(f"need lr > 0, got {lr}")
    delta = damped_step(gradient, hessian, damping, free_scalars(p, gradient, lower, upper))
    largest = float(np.max(np.abs(delta))) if delta.size else 0.0
    if largest > lr:
        delta *= lr / largest
    return np.clip(np.asarray(p, np.float64) + delta, lower, upper)


class GaussNewton(ParameterOptimizer):
    """:func:`gauss_newton_step` every iteration: the trust radius is the learning rate."""

    name = "gauss-newton"
    needs_curvature = True

    def __init__(self, damping: float, curvature: Curvature | None = None):
        if damping < 0:
            raise ValueError(f"damping must be >= 0, got {damping}")
        self.damping = damping
        self.curvature = curvature

    def step(self, p, gradient, lower, upper, *, lr, hessian=None, jacobians=None):
        return gauss_newton_step(p, gradient, self.hessian(p, lr, hessian, jacobians), lower, upper, lr=lr,
                                 damping=self.damping)

    def state_dict(self) -> dict:
        return {} if self.curvature is None else {"curvature": self.curvature.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        if self.curvature is not None and "curvature" in state:
            self.curvature.load_state_dict(state["curvature"])

"""Gauss-Newton (Levenberg-Marquardt) steps on the optimized scalars, from the gradient images.

For the ``l2`` loss ``z = (1/n) Σ (y - t)²`` over the ``n`` values of a sensor's image, with
``J = dy/dp`` the gradient images of Eq. 3, shape ``(P, H, W, 3)``, the Gauss-Newton model of
the Hessian is ``H = (2/n) JᵀJ`` (summed over sensors, as the losses are), and the step is::

    Δ = -(H + λ diag(H) + μ I)⁻¹ ∇z,        ∇z = dz/dp of Eq. 10 (the method's own estimate)
    s = min(1, lr_k / max|Δ|)                (no scalar moves more than the learning rate)
    p_{k+1} = clip(p_k + s Δ, lower, upper)

``λ`` (``damping``) is Marquardt's scaled damping; ``μ = 1e-12 · trace(H) / P`` only keeps a
scalar that no pixel depends on (zero row of ``J``, zero gradient) from making ``H`` singular.
The learning rate is a trust region of the same size as Adam's per-coordinate step.

Why it is here: when scalars trade against each other in the image (the albedo of a sphere the
camera does not see against the walls' in a bright closed room), the loss is a narrow curved
valley. Adam normalises each coordinate on its own, oscillates across the valley and crawls
along it; ``H⁻¹`` takes the coupling into account (``bench/regime.py`` measures both). Noise in a
Monte Carlo ``J`` adds its variance to ``JᵀJ`` (``E[JᵀJ] = J̄ᵀJ̄ + Σ``, mostly on the diagonal):
it damps the step, most of all along the valley, whose curvature is the smallest. ``hessian =
"cross"`` removes that bias: from two independent estimates ``J_a``, ``J_b`` (half the samples
each), ``H = (1/n) (J_aᵀJ_b + J_bᵀJ_a)`` has expectation ``(2/n) J̄ᵀJ̄``. It is noisier and may
be indefinite; the step then uses it with its eigenvalues raised to at least ``1e-6`` of the
largest (a Hessian that is already positive definite is not changed by that).
"""

from __future__ import annotations

import numpy as np


def gauss_newton_hessian(images: np.ndarray, other: np.ndarray | None = None) -> np.ndarray:
    """``(2/n) JᵀJ`` for gradient images ``J`` of shape ``(P, H, W, C)``; with ``other``, an
    independent estimate of the same ``J``, the unbiased cross product ``(1/n) (J_aᵀJ_b + J_bᵀJ_a)``
    (module docstring). Returns ``(P, P)`` float64."""
    for array in (images,) if other is None else (images, other):
        if array.ndim != 4:
            raise ValueError(f"gradient images must be (P, H, W, C), got shape {array.shape}")
    jac = images.reshape(images.shape[0], -1).astype(np.float64)
    if other is None:
        return 2.0 / jac.shape[1] * (jac @ jac.T)
    if other.shape != images.shape:
        raise ValueError(f"the two Jacobian estimates differ in shape: {images.shape} and {other.shape}")
    cross = jac @ other.reshape(other.shape[0], -1).astype(np.float64).T
    return (cross + cross.T) / jac.shape[1]


def _positive(h: np.ndarray, floor: float = 1e-6) -> np.ndarray:
    """``h`` with its eigenvalues raised to at least ``floor`` times the largest (unchanged if
    they all are already)."""
    values, vectors = np.linalg.eigh((h + h.T) / 2)
    top = max(float(values.max()), 1e-300) if values.size else 1.0
    if values.size == 0 or values.min() >= floor * top:
        return h
    return (vectors * np.maximum(values, floor * top)) @ vectors.T


def gauss_newton_step(p: np.ndarray, gradient: np.ndarray, hessian: np.ndarray, lower: np.ndarray,
                      upper: np.ndarray, *, lr: float, damping: float) -> np.ndarray:
    """One damped Gauss-Newton step (module docstring); returns the new parameters ``(P,)``."""
    g = np.asarray(gradient, np.float64)
    h = np.asarray(hessian, np.float64)
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(h))):
        raise FloatingPointError(f"non-finite parameter gradient or Gauss-Newton Hessian: {g.tolist()}")
    if h.shape != (g.size, g.size):
        raise ValueError(f"Hessian of shape {h.shape} for {g.size} scalars")
    if not lr > 0 or damping < 0:
        raise ValueError(f"need lr > 0 and damping >= 0, got lr={lr}, damping={damping}")
    h = _positive(h)
    mu = 1e-12 * max(float(np.trace(h)) / g.size, 1e-300)
    system = h + damping * np.diag(np.diag(h)) + mu * np.eye(g.size)
    delta = -np.linalg.solve(system, g)
    largest = float(np.max(np.abs(delta))) if delta.size else 0.0
    if largest > lr:
        delta *= lr / largest
    return np.clip(np.asarray(p, np.float64) + delta, lower, upper)

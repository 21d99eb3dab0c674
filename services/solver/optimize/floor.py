"""The floor of the answer's error: what the targets' own noise and the model's misfit leave in the
estimate, which no number of iterations lowers.

At the answer ``p*`` each view's residual ``t - ȳ(p*)`` is what the candidate cannot fit: a
synthetic target's Monte Carlo noise, a photograph's noise, and whatever the model misses. It
moves the minimum of the loss by ``H⁻¹ (2/n) J (t - ȳ)`` (Eq. 10 at ``p*``), whose covariance over
the views ``s`` is

    Cov_floor = H⁻¹ M H⁻¹,        M = Σ_s (2/n)² Σ_b J_{s,b} J_{s,b}ᵀ σ²_{s,b},    σ²_b = E[(t_b - ȳ_b)²]

over pixel blocks ``b`` (``J`` ``(P, n)`` averaged over the blocks the curvature averages over,
``n`` the block values of a view).

How ``σ²_b`` is read from the run. A view's candidates ``y_k`` of the answer's window, each from
``w_k`` samples per pixel, average to ``m = Σ w_k y_k / Σ w_k``, whose residual ``d = m - t`` has

    E[d_b²] = σ²_b + s²_b / Σ w_k,        s²_b = Σ w_k (y_{k,b} - m_b)² / (K - 1)

(``s²_b`` the candidates' own noise of unit weight, measured from their spread over the ``K``
candidates). So ``σ²_b = d_b² - s²_b / Σ w_k``: the candidates' noise is measured and removed,
not cancelled in pairs. (Products of consecutive residuals, the earlier estimate, carry the
candidates' full noise: with 1-spp candidates of a 256-spp target it was 250 times the quantity
read, and the demo's floor read 0.) The candidates are at the iterates ``p_k``, not at ``p*``;
``ȳ(p_k) - ȳ(p*) ≈ Jᵀ (p_k - p*)`` lies in the span of ``J``'s rows, so ``d`` and the spread are
taken off that span first (``(I - Π) r``, ``Π`` the projection on it) and block ``b``'s values
divided by ``1 - Π_bb``, the share of its variance the projection leaves. Blocks with
``Π_bb`` above :data:`MAX_LEVERAGE` (almost all ``J``) are left out. A photograph's noise and a
render's are read the same way: nothing about the target is assumed but its independence from the
candidates.

The answer's standard error is ``sqrt(SE_run² + SE_floor²)``; ``stop.auto`` ends a run once
``SE_run`` is under half of ``SE_floor`` for every scalar (:mod:`.answer`, :mod:`.stopping`).
"""

from __future__ import annotations

import numpy as np

#: The most recent candidates' residuals kept per view (each ``(n,)`` float32) ...
MAX_KEPT = 256
#: ... within this many values per view (8 MiB; at least :data:`MIN_CANDIDATES` residuals are kept).
MAX_VALUES = 1 << 21
#: The views whose candidates the floor keeps (the first seen; ``M`` is scaled to every view).
MAX_VIEWS = 8
#: The most recent Jacobians kept per view (their mean projects and weighs the window's residuals).
MAX_JACOBIANS = 8
#: The fewest candidates of a view that measure its floor (the spread needs a few).
MIN_CANDIDATES = 4
#: Blocks whose leverage ``Π_bb`` is above this hold too little of their residual off ``J`` to read it.
MAX_LEVERAGE = 0.5


def block_residual(candidate: np.ndarray, target: np.ndarray, block: int) -> np.ndarray:
    """``candidate - target`` ``(H, W, 3)`` averaged over ``block x block`` pixel blocks and
    flattened as :func:`~.optimizers.curvature.jacobian_matrix` flattens a Jacobian: ``(n,)``."""
    residual = np.asarray(candidate, np.float64) - np.asarray(target, np.float64)
    h, w, c = residual.shape
    if block <= 1 or h < block or w < block:
        return residual.reshape(-1)
    hb, wb = h // block, w // block
    return residual[:hb * block, :wb * block].reshape(hb, block, wb, block, c).mean((1, 3)).reshape(-1)


def off_span(jacobian: np.ndarray, residuals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The leverage ``Π_bb`` ``(n,)`` of each block under the projection on the rows of
    ``jacobian`` ``(P, n)``, and ``residuals`` ``(K, n)`` projected off them, ``r (I - Π)``."""
    u, singular, _ = np.linalg.svd(jacobian.T, full_matrices=False)          # u: (n, P)
    basis = u[:, singular > singular.max(initial=0.0) * 1e-8]
    return np.einsum("bi,bi->b", basis, basis), residuals - (residuals @ basis) @ basis.T


def target_variance(residuals: np.ndarray, weights: np.ndarray, jacobian: np.ndarray) -> np.ndarray:
    """``σ²_b`` ``(n,)`` of the module docstring from ``K`` candidates' block residuals ``(K, n)``
    with their samples per pixel ``weights`` ``(K,)``: unbiased, so a block's value may be
    negative (noise); left-out blocks are 0."""
    leverage, off = off_span(jacobian, residuals)
    total = float(weights.sum())
    mean = (weights[:, None] * off).sum(0) / total
    spread = (weights[:, None] * (off - mean) ** 2).sum(0) / (len(weights) - 1)
    kept = leverage <= MAX_LEVERAGE
    return np.where(kept, (mean ** 2 - spread / total) / np.where(kept, 1.0 - leverage, 1.0), 0.0)


class Floor:
    """Keeps each view's recent block residuals ``(n,)`` with their iterations and samples, and
    its recent Jacobians ``(P, n)``, for at most :data:`MAX_VIEWS` views in bounded memory;
    :meth:`covariance` reads ``Cov_floor`` over a window, with the mean of the window's Jacobians
    (or the last one before it)."""

    def __init__(self, views: int):
        if views < 1:
            raise ValueError(f"a job has at least one view, got {views}")
        self.views = views
        self.jacobians: dict[int, list[tuple[int, np.ndarray]]] = {}      # view -> [(k, J_k (P, n))]
        self.kept: dict[int, list[tuple[int, float, np.ndarray]]] = {}    # view -> [(k, w_k, r_k (n,))]

    def observe(self, k: int, view: int, residual: np.ndarray, jacobian: np.ndarray | None,
                weight: float = 1.0) -> None:
        """Iteration ``k``'s block residual ``(n,)`` of ``view`` from ``weight`` samples per pixel,
        and its Jacobian ``(P, n)`` when the iteration measured one."""
        if not weight > 0:
            raise ValueError(f"a candidate's samples per pixel must be > 0, got {weight}")
        if view not in self.kept and len(self.kept) >= MAX_VIEWS:
            return
        kept, jacobians = self.kept.setdefault(view, []), self.jacobians.setdefault(view, [])
        if kept and kept[-1][2].shape != residual.shape:    # a new film (a remesh, a resolution stage)
            kept.clear()
            jacobians.clear()
        if jacobian is not None:
            self.jacobians[view] = [*jacobians[-(MAX_JACOBIANS - 1):], (k, np.asarray(jacobian, np.float32))]
        most = min(MAX_KEPT, max(MIN_CANDIDATES, MAX_VALUES // max(residual.size, 1)))
        self.kept[view] = [*kept[-(most - 1):], (k, float(weight), np.asarray(residual, np.float32))]

    def covariance(self, start: int, h_inv: np.ndarray) -> np.ndarray | None:
        """``Cov_floor`` ``(P, P)`` from the candidates of iterations ``>= start`` (the answer's
        window); None while no view has :data:`MIN_CANDIDATES` of them and a Jacobian."""
        parts = []
        for view, kept in self.kept.items():
            window = [(w, r) for k, w, r in kept if k >= start]
            measured = self.jacobians.get(view, [])
            recent = [j for k, j in measured if k >= start] or [j for _, j in measured[-1:]]
            if not recent or len(window) < MIN_CANDIDATES or recent[0].shape[1] != window[0][1].size:
                continue
            j = np.mean(np.array(recent, np.float64), axis=0)   # a 1-spp Jacobian's noise would leave drift off its span
            weights = np.array([w for w, _ in window])
            variance = target_variance(np.array([r for _, r in window], np.float64), weights, j)
            scale = 2.0 / variance.size
            parts.append(scale * scale * (j * variance) @ j.T)
        if not parts:
            return None
        m = sum(parts) * self.views / len(parts)
        m = (m + m.T) / 2
        values, vectors = np.linalg.eigh(m)
        m = (vectors * np.clip(values, 0.0, None)) @ vectors.T   # a variance: negative estimates are noise
        return h_inv @ m @ h_inv.T

    def state_dict(self) -> dict:
        return {"jacobians": {str(v): [(k, j) for k, j in js] for v, js in self.jacobians.items()},
                "kept": {str(v): [(k, w, r) for k, w, r in kept] for v, kept in self.kept.items()}}

    def load_state_dict(self, state: dict) -> None:
        """A checkpoint's floor; one written before the candidates were kept (``pairs``) restarts
        the floor."""
        self.jacobians = {int(v): [(int(k), np.asarray(j, np.float32)) for k, j in js]
                          for v, js in state["jacobians"].items() if isinstance(js, list)}
        self.kept = {int(v): [(int(k), float(w), np.asarray(r, np.float32)) for k, w, r in kept]
                     for v, kept in state.get("kept", {}).items()}

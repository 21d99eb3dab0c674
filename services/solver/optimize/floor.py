"""The floor of the answer's error: what the targets' own noise and the model's misfit leave in the
estimate, which no number of iterations lowers.

At the answer ``p*`` each view's residual ``t - ȳ(p*)`` is what the candidate cannot fit: a
synthetic target's Monte Carlo noise, a photograph's noise, and whatever the model misses. It
moves the minimum of the loss by ``H⁻¹ (2/n) Jᵀ (t - ȳ)`` (Eq. 10 at ``p*``), whose covariance over
the views ``s`` is

    Cov_floor = H⁻¹ M H⁻¹,        M = Σ_s (2/n)² Σ_b J_{s,b} J_{s,b}ᵀ E[(t_{s,b} - ȳ_{s,b})²]

over pixel blocks ``b`` (``J`` averaged over the blocks the curvature averages over, ``n`` the
block values of a view). ``E[(t - ȳ)²]`` is estimated without the candidates' own noise: two
candidates of the same view from independent samples, ``y¹`` and ``y²``, give
``E[(y¹ - t)(y² - t)] = (ȳ - t)²``. Each view's consecutive candidates in the answer's window are
such a pair (their parameters differ by a step, whose effect on the image is second order here).

The answer's standard error is ``sqrt(SE_run² + SE_floor²)``; ``stop.auto`` ends a run once
``SE_run`` is under half of ``SE_floor`` for every scalar (:mod:`.answer`, :mod:`.recipe`).
"""

from __future__ import annotations

import numpy as np

#: The most recent pairs kept (each a ``(P, P)`` matrix).
MAX_PAIRS = 1024


def block_residual(candidate: np.ndarray, target: np.ndarray, block: int) -> np.ndarray:
    """``candidate - target`` ``(H, W, 3)`` averaged over ``block x block`` pixel blocks and
    flattened as :func:`~.optimizers.curvature.jacobian_matrix` flattens a Jacobian: ``(n,)``."""
    residual = np.asarray(candidate, np.float64) - np.asarray(target, np.float64)
    h, w, c = residual.shape
    if block <= 1 or h < block or w < block:
        return residual.reshape(-1)
    hb, wb = h // block, w // block
    return residual[:hb * block, :wb * block].reshape(hb, block, wb, block, c).mean((1, 3)).reshape(-1)


class Floor:
    """Accumulates each view's residual products (module docstring) as ``(P, P)`` matrices, one
    per pair of consecutive candidates of a view, with the iteration of the pair's second."""

    def __init__(self, views: int):
        if views < 1:
            raise ValueError(f"a job has at least one view, got {views}")
        self.views = views
        self.previous: dict[int, np.ndarray] = {}        # view -> its last block residual (n,)
        self.jacobians: dict[int, np.ndarray] = {}       # view -> its last block Jacobian (P, n)
        self.pairs: list[tuple[int, int, np.ndarray]] = []   # (iteration, view, (2/n)² J diag(r¹r²) Jᵀ)

    def observe(self, k: int, view: int, residual: np.ndarray, jacobian: np.ndarray | None) -> None:
        """Iteration ``k``'s block residual ``(n,)`` of ``view``, and its Jacobian ``(P, n)`` when
        the iteration measured one."""
        if jacobian is not None:
            self.jacobians[view] = np.asarray(jacobian, np.float64)
        before = self.previous.get(view)
        self.previous[view] = np.asarray(residual, np.float64)
        if before is None or view not in self.jacobians or before.shape != residual.shape:
            return
        j = self.jacobians[view]
        if j.shape[1] != residual.size:
            return
        scale = 2.0 / residual.size
        self.pairs = [*self.pairs[-(MAX_PAIRS - 1):], (k, view, scale * scale * (j * (before * residual)) @ j.T)]

    def covariance(self, start: int, h_inv: np.ndarray) -> np.ndarray | None:
        """``Cov_floor`` ``(P, P)`` from the pairs of iterations ``>= start`` (the answer's
        window); None before any pair."""
        by_view: dict[int, list[np.ndarray]] = {}
        for k, view, m in self.pairs:
            if k >= start:
                by_view.setdefault(view, []).append(m)
        if not by_view:
            return None
        m = sum(np.mean(ms, axis=0) for ms in by_view.values()) * self.views / len(by_view)
        m = (m + m.T) / 2
        values, vectors = np.linalg.eigh(m)
        m = (vectors * np.clip(values, 0.0, None)) @ vectors.T   # a variance: negative estimates are noise
        return h_inv @ m @ h_inv.T

    def state_dict(self) -> dict:
        return {"previous": {str(v): r for v, r in self.previous.items()},
                "jacobians": {str(v): j for v, j in self.jacobians.items()},
                "pairs": [(k, v, m) for k, v, m in self.pairs]}

    def load_state_dict(self, state: dict) -> None:
        self.previous = {int(v): np.asarray(r, np.float64) for v, r in state["previous"].items()}
        self.jacobians = {int(v): np.asarray(j, np.float64) for v, j in state["jacobians"].items()}
        self.pairs = [(int(k), int(v), np.asarray(m, np.float64)) for k, v, m in state["pairs"]]

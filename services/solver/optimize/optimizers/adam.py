"""Adam on the optimized scalars, followed by projection onto their bounds.

Update rule (Kingma & Ba 2015), for gradient ``g_t`` of step ``t = 1, 2, ...``::

    m_t = β1 m_{t-1} + (1 - β1) g_t
    v_t = β2 v_{t-1} + (1 - β2) g_t²
    p_t = clip(p_{t-1} - lr_t · m̂_t / (sqrt(v̂_t) + ε), lower, upper)

with ``m̂_t = m_t / (1 - β1^t)`` and ``v̂_t = v_t / (1 - β2^t)``. ``β1, β2`` lie in ``[0, 1)``,
``lr > 0`` and ``ε > 0``. The projection is what ``mi.ad.Adam`` does not do (an albedo would go
negative). With ``uniform`` (spans ``(start, stop)`` of ``p``), each span's ``v̂`` is replaced by its
largest entry, one step scale for the whole span: Mitsuba's ``mi.ad.Adam(uniform=True)``, which
its shape tutorial uses on a mesh's LargeSteps coordinates (per-entry scales would undo the
smoothing the parameterization gives). A non-finite gradient is refused: the caller reports it instead of writing a NaN
parameter. Adam averages Monte Carlo noise through its moments, so it never asks for a larger
batch (:meth:`~.base.ParameterOptimizer.noise_dominated` stays false).
"""

from __future__ import annotations

import numpy as np

from services.solver.optimize.optimizers.base import ParameterOptimizer, check_finite


class Adam(ParameterOptimizer):
    name = "adam"
    #: spans ``(start, stop)`` of ``p`` that share one second moment, their largest (module docstring)
    uniform: tuple[tuple[int, int], ...] = ()

    def __init__(self, size: int, lr: float, beta1: float = 0.9, beta2: float = 0.999, eps: float = 1e-8):
        if not lr > 0:
            raise ValueError(f"learning rate must be > 0, got {lr}")
        if not (0 <= beta1 < 1 and 0 <= beta2 < 1):
            raise ValueError(f"betas must lie in [0, 1), got ({beta1}, {beta2})")
        if not eps > 0:
            raise ValueError(f"eps must be > 0, got {eps}")
        self.lr, self.beta1, self.beta2, self.eps = lr, beta1, beta2, eps
        self.m = np.zeros(size)
        self.v = np.zeros(size)
        self.t = 0

    def step(self, p: np.ndarray, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray, *,
             lr: float | None = None, hessian: np.ndarray | None = None,
             jacobians: dict[int, list[np.ndarray]] | None = None) -> np.ndarray:
        """One update; returns the new (projected) parameters, shape ``(n,)``."""
        g = np.asarray(gradient, np.float64)
        check_finite(g)
        self.t += 1
        self.m = self.beta1 * self.m + (1 - self.beta1) * g
        self.v = self.beta2 * self.v + (1 - self.beta2) * g * g
        m_hat = self.m / (1 - self.beta1 ** self.t)
        v_hat = self.v / (1 - self.beta2 ** self.t)
        for start, stop in self.uniform:
            v_hat[start:stop] = np.max(v_hat[start:stop], initial=0.0)
        step = (self.lr if lr is None else lr) * m_hat / (np.sqrt(v_hat) + self.eps)
        if self.units is not None:
            step = step * self.units
        return np.clip(np.asarray(p, np.float64) - step, lower, upper)

    def state_dict(self) -> dict:
        return {"m": self.m.tolist(), "v": self.v.tolist(), "t": self.t}

    def load_state_dict(self, state: dict) -> None:
        self.m, self.v, self.t = np.asarray(state["m"], float), np.asarray(state["v"], float), int(state["t"])

"""The answer a run returns: the best estimate of the parameters from the iterations of its
current window, with a standard error per scalar, not the last noisy iterate.

Each iteration ``k`` evaluates an unbiased, independently sampled gradient ``g_k`` ``(P,)`` of the
loss summed over every view at the parameters ``p_k`` (Eq. 10; fresh seeds, views drawn without
replacement). Near the answer ``p*`` the loss is quadratic with the Gauss-Newton curvature ``H``
``(P, P)`` (:mod:`.optimizers.curvature`), so

    g_k = H (p_k - p*) + ξ_k,        E[ξ_k | p_k] = 0,        Cov ξ_k = S / w_k

with ``w_k`` the iteration's samples (views x samples per pixel of its batch: the noise falls as
the batch grows). Every iteration is then a noisy Newton estimate ``p_k - H⁻¹ g_k`` of ``p*``,
whatever step the optimizer took, and :class:`NewtonAnswer` returns their weighted mean over a
window ``W`` of iterations:

    p̂ = Σ_W w_k (p_k - H⁻¹ g_k) / Σ_W w_k                                     (the estimate)
    Cov p̂ = H⁻¹ (Σ_W w_k² r_k r_kᵀ) H⁻¹ / (Σ_W w_k)² · |W| / (|W| - P)           (its covariance)
    r_k = g_k - H (p_k - p̂)                                                    (gradient residuals)

It is unbiased to first order with the covariance of the averaged noise (Polyak & Juditsky 1992's
averaged iterate, with the Newton correction removing what the optimizer's own steps leave: a
window may start before the steps settle). ``H`` is the mean curvature of the last
:data:`CURVATURE_MEMORY` iterations; ``|W| / (|W| - P)`` corrects the residuals for the ``P``
values ``p̂`` was fitted with. Why the curvature and the gradient noise, and not the spread of the
iterates: the iterates of a trust-region method are strongly correlated (their spread over a
window says little about the error of their mean), while the gradients' noise is independent
from one iteration to the next, and the curvature that turns it into a parameter error is
measured anyway by the second-order steps.

A run without a curvature (Adam: textures, the ``l1`` loss, many scalars) has no Newton correction:
:class:`MeanAnswer` returns the window's weighted mean of the iterates, and per scalar the
batch-means error of that mean, in memory bounded whatever ``P`` (a million texels). Where the
iterates still move (Adam on its way: the batch means' least-squares trend more than
:data:`DRIFT_T` of its standard errors), the mean lags the run; the estimate is then the trend at
the window's last iteration, and its error adds the trend's own error there and the distance the
trend moved past the mean (a run that still moves goes on about as far again: iterates that
approach the truth exponentially over a third of the run were covered by ±2 SE for 74% of
scalars, none without; ``tests/unit/test_answer.py``).

The window. The model is local: far from the answer ``H`` changes and the Newton estimates of early
iterations are off. A :class:`NewtonAnswer`'s window never reaches into the first :data:`TAIL` of
the run (a suffix average, Rakhlin, Shamir & Sridharan 2012: the transient is left out whatever a
test says of it; on the demo the whole run had stayed in the window, its first iteration at the
initial values, and the floor read from those iterations stopped a run at 17 of 120 iterations).
Within that tail it is the longest suffix whose two halves give estimates that agree within the
errors the recent half's noise gives them (``χ²`` of their difference below its
:data:`~.significance.AGREEMENT` quantile, :func:`~.significance.consistent`), tried at lengths
shrinking by a quarter down to :data:`MIN_WINDOW` iterations, and never shorter than halves that
each measure their noise with two degrees of freedom (``2 (P + 2)`` iterations): a window no test
has shown settled gives its estimate with no standard error (the pose example at 20 iterations, 6
scalars: its untested 11-iteration window's ±2 SE held 40% of scalars, median |error|/SE 2.5).
So it restarts when the parameters move. (With each half's own residuals, iterations the model
does not fit widen their own error bars and pass: on the bright closed room the whole run stayed
in the window, and the errors were twice the standard errors at every budget.)

A biased gradient (a learned field's ``dz/dp``: ``ndrf-rhs``'s, a radiance cache's)
moves every Newton estimate by ``-H⁻¹ b`` for its bias ``b``, which no error of its noise holds.
Where the recipe checks it (``bias_every``), ``prb``'s unbiased ``dz/dp`` of the same views at the
same parameters gives ``d_k = g_prb,k - g_k``, ``E d_k = -b``; over the window's ``n`` checks
(:data:`MIN_CHECKS` at least)

    p̂ ← p̂ - H⁻¹ d̄,        Cov p̂ ← Cov p̂ + H⁻¹ (S_d / n) H⁻¹ (n - 1) / (n - 3)

with ``S_d`` the checks' sample covariance (the last factor: the variance of Student's ``t``,
since ``S_d`` is itself estimated from the ``n`` checks)
so the answer is unbiased to first order again, at the price of ``prb``'s noise in ``d̄``: the
field's Newton estimates carry the run, ``prb``'s differences to them only the field's bias (a
control variate: the less the two gradients differ, the less noise the correction adds). Always,
not where a test of ``d̄`` against its noise passes: a bias that test cannot see stays in the
answer, unheld by its error (on hidden-object as written, ``ndrf-rhs``, 5 seeds, no per-scalar
``t`` test passed and ±2 SE held 73%; corrected always, 100% with a median |error|/SE of 0.68,
``python -m bench.investigations.bias_check``), and a ``χ²`` of ``d̄`` with the sample covariance
of few checks passes on noise alone.

What the standard error covers: the run's own Monte Carlo noise, which averaging lowers without
end, and (:class:`NewtonAnswer`) the floor that the targets' noise and the model's misfit leave,
which no number of iterations lowers (:mod:`.floor`): ``SE = sqrt(SE_run² + SE_floor²)``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.solver.optimize.floor import Floor
from services.solver.optimize.significance import consistent

#: The fewest iterations an estimate averages (below: the last iterate, no standard error).
MIN_WINDOW = 8
#: Iterations whose curvatures are averaged into the estimate's ``H``.
CURVATURE_MEMORY = 32
#: The longest window of a :class:`NewtonAnswer` (its memory: this many ``(P,)`` iterates and gradients).
MAX_WINDOW = 8192
#: Batches of a :class:`MeanAnswer`: between this and twice this many are kept.
BATCHES = 16
#: The fewest checks of a biased gradient (:meth:`NewtonAnswer.check`) in a window its bias is corrected from
#: (four: the variance of Student's ``t`` for their mean is finite from four on).
MIN_CHECKS = 4
#: The share of the run, from its start, that no window reaches into.
TAIL = 1 / 3
#: A :class:`MeanAnswer`'s iterates still move where the trend of its batch means is more than
#: this many of its standard errors (a two-sided 5% test).
DRIFT_T = 2.0


def tail_length(seen: int) -> int:
    """The longest window after ``seen`` iterations: the run past its first :data:`TAIL`, and at
    least :data:`MIN_WINDOW` iterations."""
    return max(MIN_WINDOW, seen - int(TAIL * seen))


@dataclass(frozen=True)
class Estimate:
    """The run's answer now: ``values`` and ``standard_error`` ``(P,)`` (None while too few
    iterations were seen), the window ``[start, end]`` of iterations it averages, and how it was
    formed: ``newton`` (curvature-corrected), ``mean`` (iterates averaged) or ``last`` (the last
    iterate)."""

    values: np.ndarray
    standard_error: np.ndarray | None
    start: int
    end: int
    kind: str
    run_error: np.ndarray | None = None     # the part of the standard error the run's own noise makes
    floor_error: np.ndarray | None = None   # the part the targets' noise and the misfit make (:mod:`.floor`)

    @property
    def iterations(self) -> int:
        return self.end - self.start + 1


def newton_estimate(p: np.ndarray, g: np.ndarray, w: np.ndarray, h: np.ndarray, h_inv: np.ndarray,
                    noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(p̂ (P,), Cov p̂ (P, P), S (P, P))`` of the module docstring for iterates ``p`` and
    gradients ``g`` ``(K, P)`` with weights ``w`` ``(K,)``; ``S`` is the gradient noise of unit
    weight, measured from the residuals unless given (``noise``)."""
    k, n = p.shape
    total = float(w.sum())
    estimate = (w[:, None] * (p - g @ h_inv.T)).sum(0) / total
    if noise is None:
        residuals = g - (p - estimate) @ h.T
        noise = (w[:, None] * residuals).T @ residuals / (k - n) if k > n else np.full((n, n), np.inf)
    return estimate, h_inv @ noise @ h_inv.T / total, noise


class NewtonAnswer:
    """The answer of a run with a curvature (module docstring). ``lower``, ``upper`` ``(P,)``: the
    estimate is projected onto the bounds, as the iterates are."""

    kind = "newton"

    def __init__(self, lower: np.ndarray, upper: np.ndarray, views: int = 1, first: int = 0):
        self.lower, self.upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        self.first = first     # the iteration of the first observation (a remeshed run's stage starts later)
        self.seen = 0
        self.floor = Floor(views)
        self.points: list[np.ndarray] = []
        self.gradients: list[np.ndarray] = []
        self.weights: list[float] = []
        self.curvatures: list[np.ndarray] = []
        self.checks: list[tuple[int, np.ndarray]] = []   # (iteration, unbiased - biased dz/dp (P,))

    def check(self, k: int, difference: np.ndarray) -> None:
        """Iteration ``k``'s unbiased ``dz/dp`` (prb's) minus the method's, of the same views at the
        same parameters: the method's bias, with both noises (module docstring)."""
        self.checks = [*self.checks[-(MAX_WINDOW - 1):], (int(k), np.array(difference, np.float64))]

    def observe(self, p: np.ndarray, gradient: np.ndarray, weight: float, hessian: np.ndarray | None) -> None:
        """The next iteration: its parameters ``p`` and gradient ``(P,)``, its samples ``weight``
        and the curvature its step used."""
        if not weight > 0:
            raise ValueError(f"an iteration's weight must be > 0, got {weight}")
        self.seen += 1
        self.points = [*self.points[-(MAX_WINDOW - 1):], np.array(p, np.float64)]
        self.gradients = [*self.gradients[-(MAX_WINDOW - 1):], np.array(gradient, np.float64)]
        self.weights = [*self.weights[-(MAX_WINDOW - 1):], float(weight)]
        if hessian is not None:
            self.curvatures = [*self.curvatures[-(CURVATURE_MEMORY - 1):], np.array(hessian, np.float64)]

    def estimate(self) -> Estimate:
        """The best estimate from the iterations observed so far."""
        k = len(self.points)
        if k == 0:
            raise ValueError("no iteration observed")
        last = self.first + self.seen - 1
        if k < MIN_WINDOW or not self.curvatures:
            return Estimate(self.points[-1], None, last, last, "last")
        p, g, w = np.array(self.points), np.array(self.gradients), np.array(self.weights)
        h = np.mean(self.curvatures, axis=0)
        h = (h + h.T) / 2
        h_inv = np.linalg.pinv(h)

        def fit(a: int, b: int, noise: np.ndarray | None = None):
            return newton_estimate(p[a:b], g[a:b], w[a:b], h, h_inv, noise)

        testable = 2 * (p.shape[1] + 2)   # halves long enough to measure the noise in (2 degrees of freedom)
        length = k
        while length > tail_length(self.seen):   # the lengths tried are the whole run's, shrunk to its tail
            length = length * 3 // 4
        while length >= MIN_WINDOW:
            start, half = k - length, k - length + length // 2
            if length < testable:  # no test can show this window settled: its estimate, with no error
                values, _ = self._corrected(fit(start, k), last - length + 1, h_inv)
                return Estimate(np.clip(values, self.lower, self.upper), None, last - length + 1, last, self.kind)
            # the older half judged with the recent half's noise: iterations the quadratic model does
            # not fit would otherwise widen their own error bars and pass
            recent = fit(half, k)
            if consistent(fit(start, half, recent[2])[:2], recent[:2]):
                values, covariance = self._corrected(fit(start, k), last - length + 1, h_inv)
                run = np.clip(np.diag(covariance), 0.0, None)
                floor = self.floor.covariance(last - length + 1, h_inv)
                total = run if floor is None else run + np.clip(np.diag(floor), 0.0, None)
                return Estimate(np.clip(values, self.lower, self.upper), np.sqrt(total), last - length + 1, last,
                                self.kind, np.sqrt(run), None if floor is None else np.sqrt(np.diag(floor)))
            length = length * 3 // 4
        return Estimate(self.points[-1], None, last, last, "last")

    def _corrected(self, fitted: tuple, start: int, h_inv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """A window's Newton estimate and covariance (``fitted``), moved by what prb's checks of
        iterations ``>= start`` measured of a biased gradient (:meth:`_bias`; unmoved without)."""
        values, covariance, _ = fitted
        bias = self._bias(start, h_inv)
        return (values, covariance) if bias is None else (values - bias[0], covariance + bias[1])

    def _bias(self, start: int, h_inv: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
        """``(H⁻¹ d̄, H⁻¹ Cov d̄ H⁻¹)`` from the checks of iterations ``>= start`` (the window): the
        shift of the Newton estimate the gradients' mean bias ``-d̄`` makes, and its covariance
        (prb's noise, as the checks' spread measures it); None with fewer than :data:`MIN_CHECKS`.
        Unconditional: a test of ``d̄`` against its noise leaves every bias it cannot see in the
        answer, unheld by its error (module docstring)."""
        differences = np.array([d for k, d in self.checks if k >= start])
        if len(differences) < MIN_CHECKS:
            return None
        n = len(differences)
        # Cov d̄ from n checks' own spread: d̄'s error is Student's t with n - 1 degrees of freedom,
        # whose variance is (n - 1) / (n - 3) times the spread's estimate (a sample variance from
        # few checks is low more often than high, and the ±2 SE of a plain estimate would cover
        # 86% at n = 4, 91% at n = 8; scaled, 95-96%)
        spread = np.atleast_2d(np.cov(differences, rowvar=False)) / n * (n - 1) / (n - 3)
        return h_inv @ differences.mean(axis=0), h_inv @ spread @ h_inv.T

    def residual(self, k: int, view: int, residual: np.ndarray, jacobian: np.ndarray | None,
                 weight: float = 1.0) -> None:
        """Iteration ``k``'s block residual of ``view`` (from ``weight`` samples per pixel) and its
        Jacobian, for the floor (:mod:`.floor`)."""
        self.floor.observe(k, view, residual, jacobian, weight)

    def state_dict(self) -> dict:
        return {"first": self.first, "seen": self.seen, "points": np.array(self.points),
                "gradients": np.array(self.gradients),
                "weights": np.array(self.weights), "curvatures": np.array(self.curvatures),
                "floor": self.floor.state_dict(), "check_iterations": [k for k, _ in self.checks],
                "checks": np.array([d for _, d in self.checks])}

    def load_state_dict(self, state: dict) -> None:
        self.floor.load_state_dict(state["floor"])
        self.first, self.seen = int(state.get("first", 0)), int(state["seen"])
        self.points = [np.asarray(v, np.float64) for v in state["points"]]
        self.gradients = [np.asarray(v, np.float64) for v in state["gradients"]]
        self.weights = [float(v) for v in state["weights"]]
        self.curvatures = [np.asarray(v, np.float64) for v in state["curvatures"]]
        self.checks = [(int(k), np.asarray(d, np.float64))
                       for k, d in zip(state.get("check_iterations", []), state.get("checks", []))]


class MeanAnswer:
    """The answer of a run without a curvature (module docstring): iterates summed into batches
    of consecutive iterations, two neighbours merged whenever more than ``2 x`` :data:`BATCHES`
    are kept, so memory stays ``O(BATCHES x P)``; windows start at a batch."""

    kind = "mean"

    def __init__(self, lower: np.ndarray, upper: np.ndarray, first: int = 0):
        self.lower, self.upper = np.asarray(lower, np.float64), np.asarray(upper, np.float64)
        self.first = first     # the iteration of the first observation (a remeshed run's stage starts later)
        self.seen = 0
        self.size = 1                                  # iterations per batch now
        self.sums: list[np.ndarray] = []               # Σ w_k p_k per batch
        self.totals: list[float] = []                  # Σ w_k per batch
        self.counts: list[int] = []                    # iterations per batch
        self.last: np.ndarray | None = None

    def observe(self, p: np.ndarray, gradient: np.ndarray, weight: float, hessian: np.ndarray | None) -> None:
        if not weight > 0:
            raise ValueError(f"an iteration's weight must be > 0, got {weight}")
        self.seen += 1
        self.last = np.array(p, np.float64)
        if not self.counts or self.counts[-1] >= self.size:
            self.sums.append(np.zeros_like(self.last))
            self.totals.append(0.0)
            self.counts.append(0)
        self.sums[-1] += weight * self.last
        self.totals[-1] += weight
        self.counts[-1] += 1
        if len(self.counts) >= 2 * BATCHES and self.counts[-1] >= self.size:   # full: merge neighbours
            self.size *= 2
            self.sums = [self.sums[i] + self.sums[i + 1] for i in range(0, len(self.sums), 2)]
            self.totals = [self.totals[i] + self.totals[i + 1] for i in range(0, len(self.totals), 2)]
            self.counts = [self.counts[i] + self.counts[i + 1] for i in range(0, len(self.counts), 2)]

    def residual(self, k: int, view: int, residual: np.ndarray, jacobian: np.ndarray | None,
                 weight: float = 1.0) -> None:
        """No floor without a curvature to turn it into parameter errors."""

    def check(self, k: int, difference: np.ndarray) -> None:
        """No bias correction without a curvature to turn a gradient's bias into the parameters'
        (the recipe checks second-order runs only)."""

    def _fit(self, a: int, b: int, noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The weighted mean of batches ``a..b-1``, its per-scalar variance and the variance of a
        batch mean of unit weight (measured from the batches' spread unless given, ``noise``)."""
        total = float(sum(self.totals[a:b]))
        estimate = np.asarray(sum(self.sums[a:b]) / total, np.float64)
        if noise is None:
            n = b - a
            noise = np.asarray(sum(t * (s / t - estimate) ** 2 for s, t in zip(self.sums[a:b], self.totals[a:b])))
            noise = noise / max(n - 1, 1)
        return estimate, noise / total, noise

    def estimate(self) -> Estimate:
        if self.last is None:
            raise ValueError("no iteration observed")
        last = self.first + self.seen - 1
        batches = len(self.counts)
        if self.seen < MIN_WINDOW or batches < 4:
            return Estimate(self.last, None, last, last, "last")
        length = batches
        while length >= 4:
            start, half = batches - length, batches - length + length // 2
            recent = self._fit(half, batches)
            if length < 8 or consistent(self._fit(start, half, recent[2])[:2], recent[:2]):
                values, variance, _ = self._fit(start, batches)
                moved, moved_variance = self._drift(start, batches)
                # the trend at the window's end, with its error and as far again as it moved (module docstring)
                values, variance = values + moved, variance + moved_variance + moved ** 2
                first = self.first + self.seen - sum(self.counts[start:])
                return Estimate(np.clip(values, self.lower, self.upper), np.sqrt(np.clip(variance, 0.0, None)),
                                first, last, self.kind)
            length = length * 3 // 4
        return Estimate(self.last, None, last, last, "last")

    def _drift(self, a: int, b: int) -> tuple[np.ndarray, np.ndarray]:
        """Per scalar, how far the iterates of batches ``a..b-1`` moved past their mean, and the
        variance of that: where a weighted least-squares line through the batch means has a slope
        ``β`` of more than :data:`DRIFT_T` of its standard errors, ``β (k_end - k̄)`` (the line at
        the window's last iteration against the mean at its mean iteration ``k̄``) and
        ``(k_end - k̄)² Var β``; 0 and 0 elsewhere. A mean of iterates that still move (Adam on its
        way) lags the run, which the batch-means error of a stationary run does not hold."""
        totals = np.asarray(self.totals[a:b])
        means = np.asarray(self.sums[a:b]) / totals[:, None]
        counts = np.asarray(self.counts[a:b], np.float64)
        middles = np.cumsum(counts) - counts / 2                       # each batch's middle, in iterations
        centre = float(totals @ middles / totals.sum())
        spread = float(totals @ (middles - centre) ** 2)
        mean = totals @ means / totals.sum()
        slope = ((totals * (middles - centre)) @ (means - mean)) / spread
        residuals = means - mean - np.outer(middles - centre, slope)
        slope_variance = (totals @ residuals ** 2) / max(len(totals) - 2, 1) / spread
        moving = np.abs(slope) > DRIFT_T * np.sqrt(slope_variance)
        ahead = float(counts.sum()) - centre
        return np.where(moving, slope * ahead, 0.0), np.where(moving, ahead ** 2 * slope_variance, 0.0)

    def state_dict(self) -> dict:
        return {"first": self.first, "seen": self.seen, "size": self.size, "sums": np.array(self.sums),
                "totals": list(self.totals),
                "counts": list(self.counts), "last": self.last}

    def load_state_dict(self, state: dict) -> None:
        self.first, self.seen, self.size = int(state.get("first", 0)), int(state["seen"]), int(state["size"])
        self.sums = [np.asarray(v, np.float64) for v in state["sums"]]
        self.totals = [float(v) for v in state["totals"]]
        self.counts = [int(v) for v in state["counts"]]
        self.last = None if state["last"] is None else np.asarray(state["last"], np.float64)


Answer = NewtonAnswer | MeanAnswer


def answer_for(second_order: bool, lower: np.ndarray, upper: np.ndarray, views: int = 1, first: int = 0) -> Answer:
    """The answer of a run whose steps have a curvature (``second_order``), or not, over ``views``
    target views, from iteration ``first`` on (0, or where a remeshed mesh's stage starts)."""
    return NewtonAnswer(lower, upper, views, first) if second_order else MeanAnswer(lower, upper, first)

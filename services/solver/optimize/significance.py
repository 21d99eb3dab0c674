"""The tests the answer applies to its own numbers (:mod:`.answer`): whether two halves of a window
agree (:func:`consistent`, ``χ²``) and whether a biased gradient's checks show its bias
(:func:`biased`, Student's ``t`` per scalar), with the quantiles they need (numpy only: the
solver imports no statistics library).
"""

from __future__ import annotations

from math import lgamma
from statistics import NormalDist

import numpy as np

#: The χ² quantile two halves of a window must agree within.
AGREEMENT = 0.99
#: A biased gradient's checks correct the answer only where their mean differs from 0 at this level.
BIAS_LEVEL = 0.95


def chi2_quantile(dof: int, q: float = AGREEMENT) -> float:
    """The ``q`` quantile of ``χ²`` with ``dof`` degrees of freedom (Wilson-Hilferty; within 1%
    for dof >= 1 at q = 0.99)."""
    z = NormalDist().inv_cdf(q)
    return dof * (1 - 2 / (9 * dof) + z * np.sqrt(2 / (9 * dof))) ** 3


def consistent(first: tuple[np.ndarray, np.ndarray], second: tuple[np.ndarray, np.ndarray]) -> bool:
    """Whether two independent estimates ``(values (P,), Cov)`` agree within their errors: ``χ²``
    of their difference below the :data:`AGREEMENT` quantile. ``Cov`` is ``(P, P)``, or ``(P,)``
    for a diagonal one."""
    difference = first[0] - second[0]
    covariance = first[1] + second[1]
    if covariance.ndim == 1:
        seen = covariance > 0
        chi2 = float(np.sum(difference[seen] ** 2 / covariance[seen]))
        return chi2 <= chi2_quantile(max(int(seen.sum()), 1)) and not np.any(difference[~seen])
    scale = np.sqrt(np.clip(np.diag(covariance), 1e-300, None))
    try:
        chi2 = float(difference / scale @ np.linalg.solve(covariance / np.outer(scale, scale), difference / scale))
    except np.linalg.LinAlgError:
        return False
    return chi2 <= chi2_quantile(difference.size)


def t_quantile(q: float, dof: int) -> float:
    """The ``q`` quantile (``q`` in [0.5, 1)) of Student's ``t`` with ``dof`` >= 1 degrees of
    freedom: its density integrated by Simpson's rule and the integral inverted by bisection
    (within 1e-6 of the tabulated values)."""
    if not 0.5 <= q < 1 or dof < 1:
        raise ValueError(f"t_quantile needs 0.5 <= q < 1 and dof >= 1, got q={q}, dof={dof}")
    norm = np.exp(lgamma((dof + 1) / 2) - lgamma(dof / 2)) / np.sqrt(dof * np.pi)

    def cdf(x: float) -> float:
        t = np.linspace(0.0, x, 4001)
        density = norm * (1 + t * t / dof) ** (-(dof + 1) / 2)
        return 0.5 + (t[1] - t[0]) / 3 * float(density[0] + density[-1] + 4 * density[1:-1:2].sum()
                                                 + 2 * density[2:-1:2].sum())

    lo, hi = 0.0, 1.0
    while cdf(hi) < q:
        lo, hi = hi, 2 * hi
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if cdf(mid) < q else (lo, mid)
    return (lo + hi) / 2


def biased(differences: np.ndarray, level: float = BIAS_LEVEL) -> bool:
    """Whether checks ``d_k`` ``(n, P)`` (unbiased minus biased ``dz/dp``) show a mean bias: some
    scalar's ``t = d̄ / (s / sqrt(n))`` beyond Student's quantile for ``n - 1`` degrees of freedom,
    Šidák-corrected for the ``P`` scalars tested (a family-wise false alarm of ``1 - level``).

    Not ``χ²`` of ``d̄`` with the sample covariance: with few checks (``n`` near or below ``P``) that
    covariance is singular or nearly so, and its ``χ²`` passes on noise alone (6 scalars, 8 checks
    of unbiased gradients: an alarm in most windows, ``tests/unit/test_answer.py``); each
    correction then moves the answer by ``prb``'s noise. ``t`` per scalar needs only its own
    variance, and its quantile holds ``n``'s uncertainty in that variance."""
    n, p = differences.shape
    if n < 2:
        return False
    spread = differences.std(axis=0, ddof=1)
    mean = differences.mean(axis=0)
    tested = spread > 0
    if np.any(mean[~tested] != 0):   # a difference with no spread at all: not noise
        return True
    t = np.abs(mean[tested]) / (spread[tested] / np.sqrt(n))
    threshold = t_quantile(1 - (1 - level ** (1 / p)) / 2, n - 1)
    return bool(np.any(t > threshold))

"""The test the answer applies to its own numbers (:mod:`.answer`): whether two halves of a window
agree (:func:`consistent`, ``χ²``), with the quantile it needs (numpy only: the solver imports no
statistics library).
"""

from __future__ import annotations

from statistics import NormalDist

import numpy as np

#: The χ² quantile two halves of a window must agree within.
AGREEMENT = 0.99


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

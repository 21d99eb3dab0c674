"""The gradient methods, by their public names: the one list every layer reads.

The solver binds one class to each member (``services.solver.estimators.methods``, which fails at
import if a member has no class); the job schema, the CLI, the planner, the tests and the bench
iterate over :class:`Method`.
"""

from __future__ import annotations

from enum import StrEnum


class Method(StrEnum):
    """How ``dy/dp`` of Eq. 10 is obtained.

    ``ndrf-lhs``        query ``dL_theta`` at the first camera hit (Eq. 11)
    ``ndrf-rhs``        one bounce from the camera hit, ``dL_theta`` and ``L_phi`` at ``x'`` (Sec. 6.3)
    ``radiance-cache``  the same bounce with ``L_phi`` but indirect ``dL = 0`` (Sec. 7.1: biased)
    ``direct``          the same bounce with emitters only (biased, no field)
    ``prb``             Mitsuba's Path Replay Backpropagation integrator (the reference)
    """

    NDRF_LHS = "ndrf-lhs"
    NDRF_RHS = "ndrf-rhs"
    RADIANCE_CACHE = "radiance-cache"
    DIRECT = "direct"
    PRB = "prb"


#: The choice a job may leave to the product: measure each unbiased method on the job's own scene
#: and run the one predicted fastest (``services.solver.optimize.auto``).
AUTO = "auto"

#: The methods ``auto`` chooses among: the unbiased ones (radiance-cache and direct are baselines
#: whose gradients miss indirect terms; they are never picked for a user).
AUTO_CANDIDATES: tuple[Method, ...] = (Method.PRB, Method.NDRF_LHS, Method.NDRF_RHS)

METHOD_HELP = (
    "Gradient method: ndrf-lhs (dL_theta at the camera hit, Eq. 11), ndrf-rhs (one bounce with "
    "dL_theta and L_phi at the next hit, Sec. 6.3), radiance-cache (L_phi, indirect dL = 0), direct "
    "(emitters only), prb (Mitsuba's Path Replay Backpropagation, the reference) or auto (a short "
    "trial of prb, ndrf-lhs and ndrf-rhs on the job's own scene predicts each one's time for the "
    "job's iterations; the fastest runs, and plan.json says why)."
)

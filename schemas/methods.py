"""The gradient methods, by their public names: the one list every layer reads.

The solver binds one class to each member (``services.solver.estimators.methods``, which fails at
import if a member has no class); the job schema, the CLI, `choose_effects`, the tests and the bench
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
    ``prb-projective``  ``prb`` with projective sampling of moving silhouettes: geometry (a pose)
    ``direct-projective``  the same, direct illumination only
    """

    NDRF_LHS = "ndrf-lhs"
    NDRF_RHS = "ndrf-rhs"
    RADIANCE_CACHE = "radiance-cache"
    DIRECT = "direct"
    PRB = "prb"
    PRB_PROJECTIVE = "prb-projective"
    DIRECT_PROJECTIVE = "direct-projective"


#: The names of older versions, read as today's (one spelling per method: hyphens, as ``ndrf-lhs``).
OLDER_METHOD_NAMES = {"prb_projective": Method.PRB_PROJECTIVE.value, "direct_projective": Method.DIRECT_PROJECTIVE.value}

#: The choice a job may leave to the product (the default): no trial before the first iteration;
#: the recipe follows from the scene and the job, and the run's own iterations adjust its batch
#: (``services.solver.optimize.recipe``).
AUTO = "auto"

METHOD_HELP = (
    "Gradient method: ndrf-lhs (dL_theta at the camera hit, Eq. 11), ndrf-rhs (one bounce with "
    "dL_theta and L_phi at the next hit, Sec. 6.3), radiance-cache (L_phi, indirect dL = 0), direct "
    "(emitters only), prb (Mitsuba's Path Replay Backpropagation: unbiased), prb-projective / "
    "direct-projective (Mitsuba's projective integrators: the methods for geometry, a shape's pose) or auto "
    "(the default: prb, or a projective integrator for geometry, with the optimizer and batch chosen for the job; "
    "plan.json's recipe says what ran and why)."
)

#: The methods for geometry (a parameter that moves a shape); the others refuse it.
GEOMETRY_METHODS = (Method.PRB_PROJECTIVE, Method.DIRECT_PROJECTIVE)
#: Parameter keys that move a shape end with one of these (``services.solver.scene.geometry``).
GEOMETRY_SUFFIXES = (".to_world.translate", ".to_world.rotate")


def methods_for(keys: list[str]) -> list[Method]:
    """The methods a job of these parameter keys can run: the geometry methods when a key moves a
    shape, every other method otherwise."""
    if any(key.endswith(GEOMETRY_SUFFIXES) for key in keys):
        return list(GEOMETRY_METHODS)
    return [m for m in Method if m not in GEOMETRY_METHODS]

"""The path depth: the job's ``render.max_depth`` / ``rr_depth``, by default unbounded paths ended
by Russian roulette from depth 5 (Mitsuba's).

Rule: a truncated depth that misses more than :data:`MISSING_ENERGY` of the image's light at the
initial values (measured, :func:`~services.solver.estimators.render.missing_energy`) is a warning
in the plan.

Why: a truncation misses light, and the optimizer makes up for it with brighter materials: the
recovered parameters are biased, where Russian roulette is unbiased
(``tests/unit/test_depth_bias.py``).
"""

from __future__ import annotations

from schemas.job import JobSpec
from services.solver.estimators.render import PathDepth
from services.solver.optimize.rules.inputs import Decide, Measures

#: A truncated path depth that misses more than this share of the light is a warning in the plan.
MISSING_ENERGY = 1e-3


def path_depth(spec: JobSpec, measures: Measures, decide: Decide) -> tuple[PathDepth, list[str]]:
    """The run's path depth, and the warning of what a truncated one misses (module docstring)."""
    depth = PathDepth(spec.render.max_depth, spec.render.rr_depth)
    decide("depth", depth.describe(),
           "the job's render.max_depth / rr_depth" if spec.render.max_depth or spec.render.rr_depth != 5
           else "Mitsuba's default: every bounce, so photographs and candidates agree (no depth bias)")
    warnings = []
    if not depth.unbiased:
        missing = measures.missing_energy(depth)
        if missing > MISSING_ENERGY:
            warnings.append(f"render.max_depth {depth.max_depth} misses {missing:.1%} of the image's light at the "
                            f"initial values (more where materials are brighter): the recovered parameters are "
                            f"biased; leave render.max_depth unset for unbounded paths with Russian roulette")
    return depth, warnings

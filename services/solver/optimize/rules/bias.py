"""A biased gradient checked against ``prb``'s unbiased one.

Rule: under second-order steps on scalars (no texture, geometry or many-parameter head), a
method of :data:`BIASED_GRADIENTS` (``ndrf-rhs``'s or a radiance cache's ``dz/dp``) takes
``prb``'s unbiased ``dz/dp`` of the same views every :data:`BIAS_EVERY` iterations too, and the
answer's Newton estimate is corrected by the mean difference, its error included
(:mod:`services.solver.optimize.answer`).

Why: such a ``dz/dp`` is biased by what its fields miss, which no standard error of its own
noise holds.

Measured: ``python -m bench.coverage`` (without the check, ``ndrf-rhs`` on hidden-object as
written returned errors 1.5 times its standard errors).
"""

from __future__ import annotations

from schemas.job import JobSpec
from schemas.methods import Method
from services.solver.optimize.recipe import Steps
from services.solver.optimize.rules.inputs import Decide, Parameters

#: The methods whose biased ``dz/dp`` (a learned field's) is checked against ``prb``'s unbiased one
#: every :data:`BIAS_EVERY` iterations. Not ``ndrf-lhs``: in closed rooms, where it is chosen, the
#: checks' 1-spp prb noise moved its answer off (room-closed-8 at 30 iterations, 5 seeds: median max
#: error 0.013 checked, 0.0016 unchecked, on a 2-core AMD EPYC), though bright-room's coverage rose 30% -> 57%.
BIASED_GRADIENTS = (Method.NDRF_RHS, Method.RADIANCE_CACHE)
#: One ``prb`` adjoint render per view of every this many iterations: ten in the window of a
#: 30-iteration run (its last two thirds), at half a prb run's renders.
BIAS_EVERY = 2


def bias_check(spec: JobSpec, method: str, steps: Steps, parameters: Parameters, decide: Decide) -> int:
    """Every how many iterations ``prb``'s unbiased ``dz/dp`` checks the method's (module
    docstring; 0: never)."""
    if method not in BIASED_GRADIENTS or not steps.second_order or spec.training.head is not None \
            or parameters.has_textures or parameters.has_geometry:
        return 0
    decide("bias_every", BIAS_EVERY,
           f"{method}'s dz/dp is biased by what its fields miss, which no standard error of its own "
           f"noise holds; every {BIAS_EVERY} iterations prb's unbiased dz/dp of the same views measures that bias, "
           f"and the answer's Newton estimate is corrected by it, its error included (hidden-object as written, "
           f"bench.coverage)")
    return BIAS_EVERY

"""``auto``'s gradient method for a job of scalars (a job that moves a shape:
:func:`.geometry.geometry_method`).

Rule: ``ndrf-lhs`` in a closed scene (closure at least :data:`~.trust_region.CLOSED`), for at
most :data:`NDRF_MAX_SCALARS` scalars and no texture, every one seen directly by the cameras, an
``l2`` loss that Levenberg-Marquardt steps on with the method's own Jacobian, and a run of at
least :data:`NDRF_MIN_WORK` pixel-iterations that pays for the fields' warm-up; otherwise ``prb``
(with Russian roulette).

Why: ``prb`` gives an unbiased gradient for one adjoint render per view; with 1 spp and one view
per iteration it is the fastest hand-written Mitsuba loop in every scene measured. In a closed
scene a prb render costs more with every bounce and its forward-mode Jacobian is noise at 1 spp,
while an NDRF iteration costs the same at any depth and its Jacobian is ``dL_theta`` at the
camera hits (the candidate stays path-traced, so the answer is where the path-traced images
match).

A scalar seen only through interreflection (a hidden object) keeps ``prb``: ``dL_theta`` learns its
derivative from interreflection alone, and the field's bias stays in the answer (bright-room: its
walls' errors 5 to 10 standard errors).

Measured: ``python -m bench.pareto --jobs room-closed-8 --variant prb`` (equal seconds,
``bench/results/pareto-ndrf.md``); the cost per pixel-iteration in ``bench/results/pareto.md``; the
hidden object, ``python -m bench.pareto --jobs bright-room --budgets 1 --variant other
--loop-views none`` (80 iterations, 73 s, seeds 0-2: ``ndrf-lhs`` 0.50 (0.049-0.80), ``prb`` at the
same seconds 0.33 (0.055-0.47); at 40 iterations ``prb`` 0.54, ``ndrf-lhs`` 0.80;
``bench/results/pareto-bright.md``).
"""

from __future__ import annotations

from schemas.job import JobSpec
from schemas.methods import Method
from services.solver.optimize.rules.inputs import Decide, Measures, Parameters
from services.solver.optimize.rules.trust_region import CLOSED

#: ``auto`` trains a field (``ndrf-lhs``) in a closed scene for at most this many scalars (its
#: ``dL_theta`` has an output per scalar and channel; the closed rooms measured have six).
NDRF_MAX_SCALARS = 12
#: ... and a job of at least this many pixel-iterations (the smallest target view's pixels times the
#: iterations). prb in a closed scene costs about 140 us per pixel-iteration on 2 CPU cores, batch
#: growth and Jacobian renders included (bench/results/pareto.md: 75 s for 30 x 128², 16 s for 30 x
#: 64²), the field's warm-up 20-40 s: below this (about 37 s of prb) the warm-up does not pay.
NDRF_MIN_WORK = 1 << 18


def auto_method(spec: JobSpec, parameters: Parameters, measures: Measures, decide: Decide) -> str:
    """``auto``'s gradient method for scalars (module docstring)."""
    eligible = (spec.optimizer in ("auto", "levenberg-marquardt") and spec.loss == "l2" and spec.jacobian == "method"
                and spec.training.head is None and not parameters.has_textures and parameters.n <= NDRF_MAX_SCALARS)
    closure = measures.closure() if eligible else None
    why = ""
    if closure is not None:
        share = f"{closure:.0%} of the light a surface reflects hits another surface"
        if closure < CLOSED:
            why = f"{share} (an open scene: short paths, where a prb iteration is cheaper than training a field); "
        else:
            width, height = measures.film()
            work = width * height * spec.iterations
            size = f"{work / 2**10:.0f} Ki pixel-iterations ({NDRF_MIN_WORK / 2**10:g} Ki pay for the warm-up)"
            if work < NDRF_MIN_WORK:
                why = f"{share} (a closed scene), but only {size}: the field's warm-up would cost more than it saves; "
            elif not all(measures.direct()):
                why = (f"{share} (a closed scene), but a scalar is seen only through interreflection: dL_theta learns "
                       f"its derivative from interreflection alone, and at equal seconds prb's answer was better on "
                       f"bright-room (bench/results/pareto-bright.md); ")
            else:
                decide("method", str(Method.NDRF_LHS),
                       f"{share} (a closed scene) and {size}: light paths are long, a prb render costs more with "
                       f"every bounce and its forward-mode Jacobian is noisy, while an NDRF iteration costs the same "
                       f"at any depth and its Jacobian is a smooth field query; at equal seconds its answer was "
                       f"better on room-closed-8 (bench/results/pareto-ndrf.md)")
                return str(Method.NDRF_LHS)
    decide("method", str(Method.PRB), f"prb: {why}an unbiased gradient for one adjoint render per view, whatever the "
                                      f"number of scalars; no field to train before the first step")
    return str(Method.PRB)

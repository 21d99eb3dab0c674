"""The samples per pixel of ``prb``'s first batch, for a job of scalars that leaves them unset.

Rule: :data:`INDIRECT_SPP` samples per pixel from the first iteration where no optimized scalar
is seen directly (no active scalar changes the light of the camera's first hits: the hidden
object of the paper's Fig. 5); else 1.

Why: 1 sample per pixel is the fastest to a given error wherever a scalar is seen directly: the
optimizer averages the noise across iterations. The gradient of a scalar seen only through
interreflection is the noisy tail of longer paths, whose noise at 1 spp decides the steps'
direction.

Measured: ``python -m bench.investigations.first_spp`` (hidden-object: 1 spp reached max error
0.02 within the job's 30 iterations for 1 seed of 3, 8 spp for all 3; the demo: 1 spp at 0.76 to
0.80 s, 8 spp at 4.1 to 4.2 s).
"""

from __future__ import annotations

from collections.abc import Sequence

from schemas.job import JobSpec
from schemas.methods import Method
from services.solver.estimators.layout import DerivativeLayout
from services.solver.optimize.rules.inputs import Decide, Measures, Parameters
from services.solver.scene.effects import Effects

#: Samples per pixel of ``prb``'s first batch when no optimized scalar is seen directly.
INDIRECT_SPP = 8


def first_spp(spec: JobSpec, method: str, parameters: Parameters, effects: Effects | None, layout: DerivativeLayout,
              measures: Measures, decide: Decide, *, unset: bool) -> tuple[int, int]:
    """The first batch's samples per pixel of the candidate and of the gradient (module
    docstring); ``unset``: the job sets neither."""
    render = spec.render
    if method == Method.PRB and unset and not parameters.has_textures and indirect_only(effects, layout, measures):
        decide("spp", INDIRECT_SPP, f"no optimized scalar is seen directly: its gradient comes from paths of two "
                                    f"bounces or more, whose noise at 1 sample per pixel decides the steps' direction; "
                                    f"{INDIRECT_SPP} samples per pixel from the first iteration "
                                    f"(bench.investigations.first_spp)")
        return INDIRECT_SPP, INDIRECT_SPP
    if render.spp == 1 and render.gradient_spp == 1:
        decide("spp", 1, "1 sample per pixel: the fastest to a given error in every scene measured; the optimizer "
                         "averages the noise across iterations")
    return render.spp, render.gradient_spp


def indirect_only(effects: Effects | None, layout: DerivativeLayout, measures: Measures) -> bool:
    """True when no active scalar changes the light of the camera hits directly: from the effects
    where the method chose them, else measured (:meth:`~.inputs.Measures.direct`)."""
    if effects is not None:
        active = [s for s in effects.scalars if s.active]
        return bool(active) and all(s.first_bounce is not None and s.first_bounce > 0 for s in active)
    reach: Sequence[bool] = measures.direct()
    seen = [reach[i] for i in layout.scalars]
    return bool(seen) and not any(seen)

"""Levenberg-Marquardt's trust region, from the scene's closure (the share of the light a surface
reflects that hits another surface, :func:`services.solver.scene.closure.closure`).

Rule: where at least 1 - :data:`CLOSED` of the reflected light leaves the scene, the first step is
:data:`OPEN_START` learning rates long and the radius grows by :data:`OPEN_GROWTH` on agreeing
steps; in a closed scene, or without a reflecting surface to measure, it starts at
:data:`CLOSED_START` and grows by :data:`CLOSED_GROWTH`.

Why: an image's response to an albedo ``a`` curves like ``a / (1 - a c)`` for a closure ``c``,
and Gauss-Newton's linear model holds over long steps only where ``c`` is small.

Measured: ``python -m bench.investigations.trust_growth`` (iteration of the first max error
below 0.02, 3 seeds: the open room 3, 6, 3 with start 4 and x2 against 5, 7, 5 with start 1 and
x3/2; the closed room 7, 13, 12 with start 1 and x3/2 against 11, 9, 14 with start 4 and x2).
"""

from __future__ import annotations

from services.solver.optimize.rules.inputs import Decide, Measures

#: A scene whose closure (the share of reflected light that hits another surface) is at least this
#: is closed: its images curve strongly in the albedos, and the trust region grows slowly.
CLOSED = 0.95
#: Levenberg-Marquardt's trust-radius growth in an open scene and in a closed one.
OPEN_GROWTH, CLOSED_GROWTH = 2.0, 1.5
#: Its first radius, in learning rates, in an open scene and in a closed one.
OPEN_START, CLOSED_START = 4.0, 1.0


def trust_region(measures: Measures, decide: Decide) -> tuple[float, float]:
    """Levenberg-Marquardt's growth of the trust radius and its first radius (module docstring)."""
    closure = measures.closure()
    growth, start = CLOSED_GROWTH, CLOSED_START
    if closure is None:
        why = "no reflecting surface to measure the scene's closure on"
        growth_why = f"{why}: the cautious growth of the trust region (3/2)"
        start_why = f"{why}: the cautious first step, one learning rate (Adam's)"
    elif closure < CLOSED:
        growth, start = OPEN_GROWTH, OPEN_START
        growth_why = (f"{closure:.0%} of the light a surface reflects hits another surface: the images are close to "
                      f"linear in the scalars, and the trust region doubles on steps that agree")
        start_why = f"the same linearity: the first step may be {OPEN_START:g} learning rates long"
    else:
        growth_why = (f"{closure:.0%} of the light a surface reflects hits another surface (a closed scene): the "
                      f"images curve strongly in the albedos, and the trust region grows by 3/2 on steps that agree")
        start_why = "the same curvature: the first step is one learning rate long (Adam's)"
    decide("trust_growth", growth, growth_why)
    decide("trust_start", start, start_why)
    return growth, start

"""The derivatives a run carries (:class:`~services.solver.estimators.layout.DerivativeLayout`)
and what measuring ``prb``'s Jacobian of them costs. Derived, not chosen: the run derives them
again by the same rule after a remesh (:mod:`services.solver.optimize.remeshing`)."""

from __future__ import annotations

from services.solver.estimators.layout import DerivativeLayout
from services.solver.estimators.methods.prb import channel_groups
from services.solver.optimize.rules.inputs import Parameters
from services.solver.scene.effects import Effects


def derivative_layout(parameters: Parameters, effects: Effects | None, merge_channels: bool) -> DerivativeLayout:
    """The derivatives the run carries: the effects' active scalars and channels, else every scalar
    (each RGB component its own channel, or all three with ``merge_channels`` off)."""
    if effects is not None:
        active = effects.active_channels()
        return DerivativeLayout(tuple(i for i, _ in active), tuple(channels for _, channels in active))
    if not merge_channels:
        return DerivativeLayout.full(parameters.n)
    layout = DerivativeLayout.by_component(list(parameters.sizes))
    if parameters.has_geometry:   # a pose's three scalars are not RGB components: each changes every channel
        moves = parameters.geometry
        layout = DerivativeLayout(layout.scalars, tuple((0, 1, 2) if moves[i] else c
                                                        for i, c in zip(layout.scalars, layout.channels)))
    return layout


def jacobian_renders(layout: DerivativeLayout) -> int:
    """Forward-mode renders per view that measure ``prb``'s Jacobian (one per channel group: the
    scalars that change distinct RGB channels share one)."""
    return len(channel_groups(list(layout.channels)))

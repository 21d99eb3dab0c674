"""``Problem``: one scene with its optimized scalars, as every estimator sees it."""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from services.solver.estimators.layout import DerivativeLayout
from services.solver.sampling.surface import SurfaceSampler
from services.solver.scene.effects import Effects
from services.solver.scene.load import LoadedScene
from services.solver.scene.params import ParameterSet


@dataclass
class Problem:
    """A loaded scene, the ordered optimized scalars ``p`` (``P = parameters.n``), and what is
    simulated of it (by default everything; :meth:`simulate` narrows it to the chosen effects):

    delta_depth      ideal-specular bounces rays follow
    layout           the active scalars and the RGB channels dL_theta carries for each
    attach_bsdf      differentiate ``bsdf.eval`` (the (∂f) L term)
    attach_emission  differentiate ``emitter.eval`` (the ∂E term)
    """

    scene: LoadedScene
    parameters: ParameterSet
    delta_depth: int = 8
    layout: DerivativeLayout = field(init=False)  # every scalar, an RGB component its own channel, until simulate
    attach_bsdf: bool = True
    attach_emission: bool = True
    effects: Effects | None = None
    sanitized: dict[str, int] = field(default_factory=dict)
    refused: dict[str, int] = field(default_factory=dict)    # steps refused, by reason (never written)

    def __post_init__(self):
        layout = DerivativeLayout.by_component([info.size for info in self.parameters.infos])
        moves = [info.owner == "geometry" for info in self.parameters.infos for _ in range(info.size)]
        # a pose's three scalars are not RGB components: each changes every channel
        self.layout = DerivativeLayout(layout.scalars, tuple((0, 1, 2) if moves[i] else c
                                                             for i, c in zip(layout.scalars, layout.channels)))

    def simulate(self, effects: Effects) -> None:
        """Simulate only what ``effects`` call for."""
        self.effects = effects
        self.delta_depth = int(effects.delta_depth.value)
        self.attach_bsdf = bool(effects.bsdf_term.value)
        self.attach_emission = bool(effects.emission_term.value)
        active = effects.active_channels()
        self.layout = DerivativeLayout(tuple(i for i, _ in active), tuple(channels for _, channels in active))

    @cached_property
    def surface(self) -> SurfaceSampler:
        return SurfaceSampler(self.scene.scene)

    @property
    def bbox(self) -> tuple[np.ndarray, np.ndarray]:
        box = self.scene.scene.bbox()
        return np.array(box.min, dtype=np.float32), np.array(box.max, dtype=np.float32)

    def count_refused(self, reason: str) -> None:
        """Record a step that was refused (a shape's non-finite vertices, inverted triangles)."""
        self.refused[reason] = self.refused.get(reason, 0) + 1

    def count_sanitized(self, where: str, count: int) -> None:
        """Record lanes whose non-finite values were zeroed, so hiding a problem stays visible."""
        if count:
            self.sanitized[where] = self.sanitized.get(where, 0) + int(count)

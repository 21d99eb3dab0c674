"""What the rules read: the measurements of the scene (:class:`Measures`), the optimized
parameters (:class:`Parameters`), and how they record a choice (:data:`Decide`)."""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np

from services.solver.estimators.render import PathDepth
from services.solver.scene.facts import SceneFacts

#: ``decide(what, value, reason)``: a choice the job left to the product, with the reason ``plan.json`` shows.
Decide = Callable[[str, str | int | float, str], None]


class Measures(Protocol):
    """The measurements of the scene the rules may ask for, each at the initial values."""

    def facts(self) -> SceneFacts:
        """The effect probe (:func:`services.solver.scene.facts.probe_scene`)."""

    def closure(self) -> float | None:
        """The share of reflected light that hits another surface; None without a reflecting surface."""

    def direct(self) -> list[bool]:
        """Per scalar: whether it changes the light of the camera hits directly."""

    def missing_energy(self, depth: PathDepth) -> float:
        """The share of the image's light a truncated path ``depth`` misses."""

    def footprint(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        """``(H, W)`` pixels of the target views that see each texel of the texture ``key`` directly."""

    def film(self) -> tuple[int, int]:
        """The smallest target view's ``(width, height)`` in pixels."""


class Parameters(Protocol):
    """What the rules read of the optimized parameters (a ``ParameterSet``)."""

    @property
    def n(self) -> int: ...

    @property
    def has_textures(self) -> bool: ...

    @property
    def has_geometry(self) -> bool: ...

    @property
    def geometry(self) -> list[bool]:
        """Per scalar: whether it moves a shape."""

    def step_units(self) -> np.ndarray:
        """Per scalar: one unit of the optimizer's steps, in the scalar's own units."""

    def shape_spans(self) -> list[tuple[int, int]]:
        """``(start, stop)`` of each shape parameter (a mesh's vertices) in ``p``."""

    def flat_meshes(self) -> list[str]:
        """The posed or reshaped meshes without vertex normals."""

    @property
    def sizes(self) -> list[int]: ...

    @property
    def textures(self) -> list[tuple[str, tuple[int, ...]]]:
        """``(key, (H, W, C))`` of each texture parameter."""

"""One training step's statistics and the narrow interface a step schedule drives.

:class:`~services.solver.training.schedule.StepSchedule` decides how many steps an iteration
takes from the statistics alone; it needs nothing of the trainer but :class:`Steps`, so the
schedule and the trainer do not import each other.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Protocol


@dataclass
class StepStats:
    """One training step: residual norms (in output-scale units) and seconds (in total and per
    field, sampling included).

    ``*_loss`` is the training loss (Eq. 8, noise of the right-hand side included); ``*_residual``
    the same norm without that noise (:func:`~services.solver.training.residuals.debiased_residual`),
    which keeps falling while the field improves. ``batch`` identifies a pooled batch.
    """

    radiance_loss: float | None
    differential_loss: float | None
    seconds: float
    radiance_seconds: float = 0.0
    differential_seconds: float = 0.0
    radiance_residual: float | None = None
    differential_residual: float | None = None
    batch: tuple[int, int] | None = None


class Steps(Protocol):
    """What a schedule drives: a step counter, one step, and a number of steps."""

    steps: int

    def step(self) -> StepStats: ...

    def train(self, steps: int, on_step: Callable[[StepStats], None] | None = None) -> list[StepStats]: ...

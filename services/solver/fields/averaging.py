"""``WeightAverage``: an exponential moving average of a field's weights (Polyak averaging).

The residual losses (Eq. 8, 9) are Monte Carlo estimates: every Adam step moves the weights by
the noise of its batch as well as by the residual's mean, and the last iterate carries that noise.
The average of the iterates carries less of it. After training step ``k`` of the current average:

    w̄_k = β_k w̄_(k-1) + (1 - β_k) w_k,     β_k = min(β, (1 + k) / (10 + k))

(the second term lets a young average follow the weights instead of its first iterate). The fields
are trained with their live weights ``w`` (both residuals' right-hand sides included); queries
(gradients at camera hits, the field candidate image) read ``w̄``.

The average restarts (``k = 0``) whenever the scene's parameters change: the fields then solve a
different rendering equation and iterates of the old one would lag the new answer. In a job that
fine-tunes ``s`` steps per parameter step, ``w̄`` averages within those ``s`` steps; a field
trained at fixed parameters (warm-up, ``bench.core_accuracy``) averages over ``1 / (1 - β)``.
"""

from __future__ import annotations

import copy

import numpy as np
import torch
from torch import nn


class WeightAverage:
    """The averaged copy ``average`` of ``field`` (same class, no gradients), updated by
    :meth:`update` after each optimizer step of ``field``."""

    def __init__(self, field: nn.Module, decay: float):
        if not 0.0 <= decay < 1.0:
            raise ValueError(f"the averaging decay β must be in [0, 1), got {decay}")
        self.field = field
        self.decay = decay
        self.average = copy.deepcopy(field).requires_grad_(False)
        self.count = 0
        self.values_at: np.ndarray | None = None

    def update(self, values: np.ndarray) -> None:
        """Fold the field's current weights into the average; ``values`` are the scene parameters
        the step trained for (shape ``(n,)``): a change restarts the average."""
        if self.values_at is None or not np.array_equal(values, self.values_at):
            self.count, self.values_at = 0, np.array(values, copy=True)
        beta = min(self.decay, (1 + self.count) / (10 + self.count))
        with torch.no_grad():
            torch._foreach_lerp_(list(self.average.parameters()), list(self.field.parameters()), 1.0 - beta)
            for mine, live in zip(self.average.buffers(), self.field.buffers()):
                mine.copy_(live)  # output scale and normalisation: set once, never averaged
        self.count += 1

    def state_dict(self) -> dict:
        return {"average": self.average.state_dict(), "count": self.count,
                "values_at": None if self.values_at is None else self.values_at.tolist()}

    def load_state_dict(self, state: dict) -> None:
        self.average.load_state_dict(state["average"])
        self.count = int(state["count"])
        self.values_at = None if state["values_at"] is None else np.asarray(state["values_at"], dtype=np.float64)

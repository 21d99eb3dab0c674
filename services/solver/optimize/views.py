"""Mini-batches of target views: which views an iteration renders, and how their losses scale.

The views form a stream: the concatenation of seeded permutations of the job's ``S`` target
sensors, one per pass (``derive_seed(seed, "views", pass)``). Iteration ``k`` takes the next
``b_k`` distinct views of the stream from its position ``offset_k`` (a view already in the batch
is skipped); a batch of every view is the sorted list of sensors. The position is the only state,
so a resumed run that restores it draws the same batches as the uninterrupted run, and every view
is seen once per pass (sampling without replacement has less variance than independent draws).

Scaling. The job's loss is the sum over views of each view's loss (``z = Σ_s z_s``). A batch ``B``
estimates it, its gradient and its Gauss-Newton curvature without bias by ``(S / |B|) Σ_{s∈B}``:
:attr:`Batch.scale`. Adam is invariant to the scale; the second-order steps need the gradient and
the curvature from the same batch at the same scale, which is how the loop assembles them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.solver.seeds import derive_seed


@dataclass(frozen=True)
class Batch:
    sensors: list[int]   # the views of the iteration
    scale: float         # S / |B|
    offset: int          # the stream position after the batch


class ViewStream:
    """The seeded stream of views of a job (module docstring)."""

    def __init__(self, sensors: list[int], seed: int):
        if not sensors:
            raise ValueError("a job needs at least one target view")
        self.sensors = sorted(sensors)
        self.seed = seed
        self._order: tuple[int, list[int]] | None = None   # the last pass's permutation (a generator costs ~1 ms)

    def _at(self, position: int) -> int:
        count = len(self.sensors)
        passes, index = divmod(position, count)
        if self._order is None or self._order[0] != passes:
            rng = np.random.default_rng(derive_seed(self.seed, "views", passes))
            self._order = (passes, [self.sensors[int(i)] for i in rng.permutation(count)])
        return self._order[1][index]

    def batch(self, offset: int, size: int) -> Batch:
        """``size`` distinct views from stream position ``offset`` (every view when ``size >= S``)."""
        if size < 1:
            raise ValueError(f"a batch needs at least one view, got {size}")
        count = len(self.sensors)
        if size >= count:
            return Batch(list(self.sensors), 1.0, offset)
        chosen: list[int] = []
        position = offset
        while len(chosen) < size:
            view = self._at(position)
            position += 1
            if view not in chosen:
                chosen.append(view)
        return Batch(chosen, count / size, position)

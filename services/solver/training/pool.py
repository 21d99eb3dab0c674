"""A pool of residual batches reused across training steps (the Monte Carlo estimates of Eq. 8, 9).

Geometry is fixed in every job the product accepts (only BSDF and emitter values change), so what
a residual batch costs besides the fields can be paid once and reused:

* the residual points ``(x, ω_o)`` and their density (Eq. 8),
* their ``M`` incident directions, densities, MIS weights and hits ``x'`` (Eq. 9; the densities
  they were sampled with stay valid importance weights when the BSDF changes, see
  :class:`services.solver.sampling.incident.IncidentGeometry`),
* the hash-grid corner indices, trilinear weights and direction features of every ``x`` and
  ``x'`` (:meth:`NeuralField.precompute`), which were half of a fresh step.

Only ``emitted``, ``throughput`` and their derivatives are re-evaluated, on the stored geometry,
when the scene's parameters have changed since the batch last saw them.

The pool holds ``chunks`` batches; step ``s`` trains on batch ``s mod chunks``, and a batch is
redrawn (fresh samples) after ``reuse`` steps. Over ``S`` steps the fields therefore see
``S / reuse`` independent batches instead of ``S``: the right-hand sides' noise is averaged over
fewer samples, and a finite network can fit the noise of a batch it sees repeatedly. Both effects
shrink as ``chunks`` grows (a batch is revisited only every ``chunks`` steps, between which the
network has moved on ``chunks - 1`` other batches) and are removed by ``reuse = 1`` (every batch
fresh). Sampling, tracing and the encoding lookups cost ``1 / reuse`` of a fresh step's; memory
is ``chunks · N · M`` incident samples (about 0.4 KiB each with the cached lookups).

Shapes: ``N`` points per batch, ``M`` incident samples per point.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from services.solver.estimators.problem import Problem
from services.solver.fields.field import NeuralField
from services.solver.seeds import derive_seed
from services.solver.training.residuals import BatchGeometry, ResidualBatch, draw_geometry, evaluate_batch

log = logging.getLogger(__name__)


@dataclass
class _Slot:
    geometry: BatchGeometry
    drawn_at: int                        # the step whose seed drew it
    values_at: np.ndarray | None = None  # parameters ``batch`` was evaluated for
    batch: ResidualBatch | None = None


class ResidualPool:
    """``chunks`` residual batches of ``n`` points and ``m`` incident samples, each trained on
    ``reuse`` times before it is redrawn; see the module docstring for the trade-off.

    ``fields``: the fields that will be evaluated on the batches (their encoding inputs are
    precomputed once per batch). ``derivatives``: evaluate ``∂emitted`` / ``∂throughput`` too (for
    the differential residual, Eq. 6).
    """

    def __init__(self, problem: Problem, n: int, m: int, *, chunks: int, reuse: int, derivatives: bool,
                 fields: list[NeuralField], seed: int, camera_fraction: float = 0.0):
        if chunks < 1 or reuse < 1:
            raise ValueError(f"a pool needs chunks >= 1 and reuse >= 1, got {chunks}, {reuse}")
        self.problem, self.n, self.m = problem, n, m
        self.chunks, self.reuse, self.derivatives = chunks, reuse, derivatives
        self.fields, self.seed, self.camera_fraction = fields, seed, camera_fraction
        self.slots: dict[int, _Slot] = {}
        self.draws = 0        # batches drawn (sampling + tracing + encoding lookups)
        self.evaluations = 0  # BSDF/emitter evaluations (one per draw, plus one per stale use)

    def batch_id(self, step: int) -> tuple[int, int]:
        """``(slot, step it was drawn at)`` of the batch of training step ``step``: a pure function
        of ``step``, so a resumed run trains on the samples an uninterrupted run would have."""
        return step % self.chunks, step - ((step // self.chunks) % self.reuse) * self.chunks

    def batch(self, step: int) -> ResidualBatch:
        """The batch of training step ``step``, up to date with the scene's current parameters."""
        index, drawn_at = self.batch_id(step)
        slot = self.slots.get(index)
        if slot is None or slot.drawn_at != drawn_at:
            slot = self.slots[index] = _Slot(self._draw(drawn_at), drawn_at)
        values = self.problem.parameters.values()
        if slot.batch is None or slot.values_at is None or not np.array_equal(values, slot.values_at):
            slot.batch, slot.values_at = evaluate_batch(self.problem, slot.geometry, self.derivatives), values
            self.evaluations += 1
        return slot.batch

    def _draw(self, step: int) -> BatchGeometry:
        g = draw_geometry(self.problem, self.n, self.m, derive_seed(self.seed, "train", step, 0), self.camera_fraction)
        for field in self.fields:
            field.precompute(g.points)
            field.precompute(g.hits)
        self.draws += 1
        return g

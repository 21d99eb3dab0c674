"""How a run talks to its host: the :class:`RunReporter` protocol and the :class:`RunOutcome`.

The loop computes; it never writes files, records or events. The host decides where reports go:
``services.jobs.artifacts.JobWriter`` writes them into the artifact store (the CLI and the
worker's parent process), ``services.jobs.child`` forwards them from the sandboxed child process
to its parent, and tests collect them in memory.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Protocol

import numpy as np

from schemas.outcomes import Outcome
from schemas.records import IterationRecord

#: What a host may ask a running job for (:data:`schemas.outcomes.STOPS`).
StopReason = Literal[Outcome.CANCELED, Outcome.INTERRUPTED]


class RunReporter(Protocol):
    """What a run reports, in order: ``plan``, ``targets``, then ``progress`` (warm-up, resume),
    ``iteration`` and ``checkpoint`` as they happen. Any exception a reporter raises stops the run
    and reaches the host unchanged (a fenced attempt, a full store)."""

    def plan(self, plan: dict) -> None:
        """What the run simulates: resolved settings, scalars, bounds, fields, effects."""

    def targets(self, images: dict[int, np.ndarray]) -> None:
        """Target image of every sensor, ``(H, W, 3)`` float32 linear RGB."""

    def progress(self, kind: str, payload: dict) -> None:
        """Signs of life between iterations: ``warmup`` (steps done of planned, residual norms),
        ``resumed`` (the iteration a resumed run continues from)."""

    def iteration(self, record: IterationRecord, renders: dict[int, np.ndarray] | None,
                  gradients: dict[int, np.ndarray] | None, silhouettes: dict[int, np.ndarray] | None = None) -> None:
        """One iteration; ``renders`` (sensor -> ``(H, W, 3)``) and ``gradients`` (sensor ->
        ``(P, H, W, 3)`` float32) only on iterations that write images, and then a geometry job's
        ``silhouettes`` (sensor -> ``(H, W, 3)`` in display space, :mod:`~.images`)."""

    def textures(self, iteration: int | None, images: dict[str, np.ndarray]) -> None:
        """A texture job's textures ``(H, W, C)`` float32 by name: at an iteration that writes
        images (``<key>`` the parameters the step was taken at, ``<key>.dz_dp`` its gradient), and
        at the end (``iteration`` None: the recovered ``<key>``)."""

    def meshes(self, iteration: int, files: dict[str, bytes]) -> None:
        """A shape job's optimized meshes as PLY files, by shape id, at an iteration that writes
        images (the mesh the step was taken at)."""

    def checkpoint(self, state: bytes, next_iteration: int) -> None:
        """Everything needed to continue at ``next_iteration`` (see ``optimize.checkpoint``)."""

    def should_stop(self) -> StopReason | None:
        """Polled between training steps and iterations: None to go on."""

    def images_requested(self) -> bool:
        """Polled once per iteration: whether someone asked for the images now (the dashboard);
        the iteration then writes them whatever the schedule."""


class RunAborted(Exception):
    """Raised by a host's reporter to end the run without recording anything (it propagates
    through the loop untouched)."""


@dataclass
class RunOutcome:
    """How a run ended. ``interrupted``: the host asked it to stop and will resume it later from
    its last checkpoint (written before returning)."""

    status: Outcome  # never ``fenced``: that is the host's verdict on an attempt, not the run's
    iterations: int
    seconds: float
    estimate: list[float] | None = None          # the answer: the estimate of every listed scalar
    error: str | None = None
    field: str | None = None
    standard_error: list[float] | None = None    # of each scalar of ``estimate`` (None: no settled window)
    last_iterate: list[float] | None = None      # the parameters of the last step, not averaged
    estimate_kind: str | None = None             # how the answer was formed (schemas.summary.Summary)
    estimate_window: list[int] | None = None
    run_error: list[float] | None = None
    floor_error: list[float] | None = None
    stopped: dict | None = None                  # why the run stopped: the decision, with its reason
    poses: list[dict] | None = None              # each posed shape's answer: 4x4 matrix and XML <transform>
    #: each optimized mesh's answer, by shape id: ``ply`` (base64 of a binary PLY), vertices, faces, chamfer
    meshes: dict[str, dict] | None = None

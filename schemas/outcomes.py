"""How a run ends: one vocabulary for the loop, the attempt that supervised it and the worker.

The loop returns a ``RunOutcome`` whose ``status`` is an :class:`Outcome`; a host asks it to stop
with one of :data:`STOPS` (``RunReporter.should_stop``); the attempt a worker supervises ends with an
``AttemptResult`` carrying an :class:`Outcome`, which can also be ``fenced``; the worker acts on that
(ack, hand back, or leave the job to its new owner). The job's own status is a :class:`JobStatus`.
"""

from __future__ import annotations

from enum import StrEnum

from schemas.records import JobStatus


class Outcome(StrEnum):
    """How a run or an attempt ended."""

    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"
    #: The host stopped the run (a worker shutting down, Ctrl-C): it checkpointed, and the job goes
    #: back to the queue to resume from there.
    INTERRUPTED = "interrupted"
    #: Another attempt owns the job (its lease was lost): this one wrote nothing more (attempts only).
    FENCED = "fenced"

    @property
    def job_status(self) -> JobStatus | None:
        """The job's status after an attempt ended so: finished, ``queued`` again (interrupted),
        or None (fenced: the job is another attempt's)."""
        return _JOB_STATUS.get(self)


#: What a host may ask a running job for: stop for good, or stop to resume later.
STOPS: frozenset[Outcome] = frozenset({Outcome.CANCELED, Outcome.INTERRUPTED})

_JOB_STATUS = {Outcome.SUCCEEDED: JobStatus.SUCCEEDED, Outcome.FAILED: JobStatus.FAILED,
               Outcome.CANCELED: JobStatus.CANCELED, Outcome.INTERRUPTED: JobStatus.QUEUED}

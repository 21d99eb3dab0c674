"""Interfaces of the queue, of the event bus and of the stream slots (Redis and in-process
implementations).

The queue's contract, which both implementations keep:

* **one marker per job**: ``enqueue`` of a job that is already waiting, leased or running is a
  no-op (the reconciler and a hand-back can never put two entries of one job in the queue);
* **a lease per delivery, a heartbeat per attempt**: a worker that runs a job renews, in one
  atomic step, its ownership of the delivery and the heartbeat of its attempt (a key that expires
  ``lease_seconds`` after the last renewal). An attempt is *alive* while its heartbeat is; a
  delivery whose owner stopped renewing for ``lease_seconds`` is handed to the next worker, which
  counts a crash only if the attempt the record names is no longer alive;
* **a fair share per key**: waiting jobs are kept per owner (the hash of the API key that
  submitted them) and ``lease`` hands out the next job of the owner served least recently, so a
  key's job waits for at most one job of each other key per free worker, never for another key's
  whole queue. A job handed back (``requeue``: it was running) goes ahead of every waiting one;
* **acks are owned**: ``ack`` and ``requeue`` act only on a delivery the caller still owns (or on
  the attempt it adopted after the queue lost its data): a stale attempt never removes the
  delivery of the worker that took its job over.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Iterable
from contextlib import AbstractContextManager
from dataclasses import dataclass
from enum import Enum


@dataclass(frozen=True)
class Lease:
    """A delivery of a job to one consumer, until it acks or stops renewing for a lease period.

    ``delivery`` counts how many times this queue entry has been handed out (1 = first delivery).
    """

    job_id: str
    entry_id: str
    delivery: int
    consumer: str = ""


class Renewal(Enum):
    """What :meth:`JobQueue.renew` found."""

    KEPT = "kept"          # still ours; heartbeat refreshed
    ADOPTED = "adopted"    # the queue had lost the delivery (Redis restarted empty): the running attempt
    #                        was re-registered (marker + heartbeat) and goes on
    LOST = "lost"          # another consumer owns the delivery, or the job was queued anew: stop

    def __bool__(self) -> bool:
        return self is not Renewal.LOST


class LockBusy(Exception):
    """A per-key lock stayed held by someone else for the whole wait."""


class JobQueue(ABC):
    """At-least-once queue of job ids with owned deliveries, attempt heartbeats and a fair share
    of the workers per owner."""

    lease_seconds: float = 30.0

    @abstractmethod
    def enqueue(self, job_id: str, *, unless_alive: str | None = None, owner: str = "") -> bool:
        """Queue the job in ``owner``'s share unless it already is (waiting, leased or running),
        or, with ``unless_alive``, unless that attempt of it is alive. True if an entry was added."""

    @abstractmethod
    def withdraw(self, job_id: str, owner: str = "") -> bool:
        """Take a job that still waits in ``owner``'s share out of the queue (it was canceled while
        queued): it is never handed to a worker and spends none of its owner's turns. A job
        already handed out is left alone (its runner sees the cancel). True if it was waiting."""

    @abstractmethod
    def lease(self, consumer: str, block_seconds: float) -> Lease | None:
        """The next job for ``consumer``: first a delivery whose owner stopped renewing for a lease
        period, then a job handed back, then the next waiting job of the owner served least
        recently; ``None`` after ``block_seconds`` without work."""

    @abstractmethod
    def hold(self, name: str, seconds: float = 60.0, wait: float = 30.0) -> AbstractContextManager[None]:
        """A lock on ``name`` shared by every process of the queue (a per-key count is checked and
        taken under it in one step: :meth:`services.jobs.service.JobService.submit`). Held at most
        ``seconds`` (a holder that died frees it then); :class:`LockBusy` after ``wait``."""

    @abstractmethod
    def renew(self, lease: Lease, attempt: str) -> Renewal:
        """Atomically: if ``lease`` is still the caller's, reset its idle time and refresh the
        heartbeat of ``attempt``. A delivery the queue lost (not owned by anyone, the job not
        queued anew) is adopted; one owned by another consumer is :attr:`Renewal.LOST`."""

    @abstractmethod
    def alive(self, job_id: str, attempt: str) -> bool:
        """Whether that attempt's heartbeat has not expired."""

    @abstractmethod
    def ack(self, lease: Lease, attempt: str | None = None) -> bool:
        """The delivery is done: remove it (and the job's marker, and the attempt's heartbeat) if
        the caller still owns it. False (nothing removed) if another consumer owns it now."""

    @abstractmethod
    def requeue(self, lease: Lease, attempt: str | None = None) -> bool:
        """Hand the job back in one step: ack the caller's delivery and queue a new one (the job
        was interrupted). False if the caller no longer owned the delivery."""

    @abstractmethod
    def depth(self) -> dict[str, int]:
        """``{"waiting": ..., "leased": ...}``."""

    @abstractmethod
    def running(self, owner: str) -> int:
        """Jobs of ``owner`` handed to workers and not yet acked (at most the queue's
        ``running_per_owner``, ``NDRF_MAX_RUNNING_JOBS_PER_KEY``, when set: a worker takes another
        owner's job rather than pass it)."""

    @abstractmethod
    def queued_ids(self) -> set[str]:
        """Job ids the queue holds (waiting, leased, or adopted while running), for the reconciler."""

    @abstractmethod
    def orphans(self, candidates: Iterable[str], grace_seconds: float) -> set[str]:
        """Of ``candidates`` (unfinished jobs the queue does not hold), those that were candidates
        in every call for at least ``grace_seconds``: a live attempt re-registers itself well
        within that time after the queue lost its data, so only real orphans are re-enqueued.
        Jobs not among ``candidates`` are forgotten."""


class EventBus(ABC):
    """Live push of job events. The store's ``events.jsonl`` is the durable copy every reader
    replays from; the bus tells readers *when* to look, without polling."""

    @abstractmethod
    def publish(self, job_id: str, event: dict) -> None: ...

    @abstractmethod
    def wait(self, job_id: str, after_seq: int, timeout: float) -> bool:
        """Block until an event with ``seq > after_seq`` has been published (True) or ``timeout``
        seconds passed (False)."""

    @abstractmethod
    async def wait_async(self, job_id: str, after_seq: int, timeout: float) -> bool:
        """:meth:`wait` on the event loop, holding no thread while it waits."""

    async def aclose(self) -> None:  # noqa: B027 (a hook with a default)
        """Release the event loop's connections (no-op in-process)."""


class SlotsUnavailable(Exception):
    """The count of open streams cannot be read now (Redis away or busy): the stream is refused
    (503 with ``Retry-After``), never let in uncounted."""


class StreamSlots(ABC):
    """Open event streams per key, counted across every API process that shares the queue. Guards
    the per-key stream cap (``NDRF_MAX_STREAMS_PER_KEY``): job and experiment streams, opened with
    the key or with a read token it was given, all count against the key."""

    #: A slot not refreshed for this long is free again (its API process died).
    ttl_seconds: float = 60.0

    @abstractmethod
    async def acquire(self, owner: str, cap: int) -> str | None:
        """A slot id, or None if ``owner`` already holds ``cap`` open streams. Raises
        :class:`SlotsUnavailable` when the count cannot be read (fails closed)."""

    @abstractmethod
    async def refresh(self, owner: str, slot: str) -> None:
        """Keep a long stream's slot (call at least every ``ttl_seconds / 3``)."""

    @abstractmethod
    async def release(self, owner: str, slot: str) -> None: ...

"""Interfaces of the queue and of the event bus (Redis and in-process implementations)."""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass


@dataclass(frozen=True)
class Lease:
    """A job handed to one worker until it acks, or until it stops renewing for a lease period.

    ``delivery`` counts how many times this queue entry has been handed out (1 = first attempt);
    a job that keeps killing its worker is recognised by it.
    """

    job_id: str
    entry_id: str
    delivery: int


class JobQueue(ABC):
    """At-least-once queue of job ids."""

    @abstractmethod
    def enqueue(self, job_id: str) -> None: ...

    @abstractmethod
    def lease(self, consumer: str, block_seconds: float) -> Lease | None:
        """The next job for ``consumer``: first a job abandoned by a dead worker (its lease
        expired), otherwise a new one; ``None`` after ``block_seconds`` without work."""

    @abstractmethod
    def renew(self, lease: Lease, consumer: str) -> bool:
        """Keep the lease; False if it was lost (another worker took the job over)."""

    @abstractmethod
    def ack(self, lease: Lease) -> None:
        """The job is done (finished, failed or canceled): remove it from the queue."""

    @abstractmethod
    def depth(self) -> dict[str, int]:
        """``{"waiting": ..., "leased": ...}``."""

    @abstractmethod
    def queued_ids(self) -> set[str]:
        """Job ids currently in the queue (waiting or leased), for the reconciler."""


class EventBus(ABC):
    """Live push of job events. The store's ``events.jsonl`` is the durable copy every reader
    replays from; the bus tells readers *when* to look, without polling."""

    @abstractmethod
    def publish(self, job_id: str, event: dict) -> None: ...

    @abstractmethod
    def wait(self, job_id: str, after_seq: int, timeout: float) -> bool:
        """Block until an event with ``seq > after_seq`` has been published (True) or ``timeout``
        seconds passed (False)."""

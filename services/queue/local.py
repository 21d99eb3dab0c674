"""The embedded default: an in-process queue and event bus (no Redis). One process only."""

from __future__ import annotations

import itertools
import queue
import threading
from collections import defaultdict

from services.queue.base import EventBus, JobQueue, Lease


class LocalJobQueue(JobQueue):
    def __init__(self):
        self._queue: queue.Queue[tuple[str, str]] = queue.Queue()
        self._leased: dict[str, str] = {}
        self._ids = itertools.count(1)
        self._lock = threading.Lock()

    def enqueue(self, job_id: str) -> None:
        self._queue.put((job_id, str(next(self._ids))))

    def lease(self, consumer: str, block_seconds: float) -> Lease | None:
        try:
            job_id, entry = self._queue.get(timeout=max(0.01, block_seconds))
        except queue.Empty:
            return None
        with self._lock:
            self._leased[entry] = job_id
        return Lease(job_id, entry, 1)

    def renew(self, lease: Lease, consumer: str) -> bool:
        return lease.entry_id in self._leased

    def ack(self, lease: Lease) -> None:
        with self._lock:
            self._leased.pop(lease.entry_id, None)

    def depth(self) -> dict[str, int]:
        return {"waiting": self._queue.qsize(), "leased": len(self._leased)}

    def queued_ids(self) -> set[str]:
        with self._lock, self._queue.mutex:
            return {job for job, _ in self._queue.queue} | set(self._leased.values())


class LocalEventBus(EventBus):
    def __init__(self, keep: int = 10000):
        self._events: dict[str, list[dict]] = defaultdict(list)
        self._changed = threading.Condition()
        self._keep = keep

    def publish(self, job_id: str, event: dict) -> None:
        with self._changed:
            events = self._events[job_id]
            events.append(event)
            del events[:-self._keep]
            self._changed.notify_all()

    def wait(self, job_id: str, after_seq: int, timeout: float) -> bool:
        def newer():
            events = self._events.get(job_id)
            return bool(events) and events[-1]["seq"] > after_seq

        with self._changed:
            return self._changed.wait_for(newer, timeout)

"""The embedded default: an in-process queue, event bus and stream slots (no Redis). One process.

The queue keeps the contract of :mod:`services.queue.base` with a lock instead of Lua: one marker
per job, owned deliveries, heartbeats that expire, the takeover of a delivery whose runner
stopped renewing (an embedded runner thread that died and was restarted picks its job up again),
and waiting jobs kept per owner, served least recently served owner first.
The event bus wakes threads with a condition and event-loop waiters with futures resolved through
``call_soon_threadsafe`` (publishers are worker threads).
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import threading
import time
import uuid
from collections import defaultdict, deque
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

from services.queue.base import EventBus, JobQueue, Lease, LockBusy, Renewal, StreamSlots


@dataclass
class _Delivery:
    job_id: str
    consumer: str
    renewed: float
    count: int


class LocalJobQueue(JobQueue):
    def __init__(self, lease_seconds: float = 30.0, running_per_owner: int = 0):
        self.lease_seconds, self.running_per_owner = lease_seconds, running_per_owner
        self._running: dict[str, set[str]] = defaultdict(set)   # owner -> jobs handed out, not acked
        self._job_owner: dict[str, str] = {}
        self._ready: deque[tuple[str, str, int]] = deque()      # handed back: (job, entry, deliveries so far)
        self._waiting: dict[str, deque[tuple[str, str, int]]] = {}   # owner -> its waiting jobs
        self._served: dict[str, int] = {}                       # owner -> turn it was last served at
        self._turns = itertools.count(1)
        self._locks: dict[str, threading.Lock] = defaultdict(threading.Lock)
        self._leased: dict[str, _Delivery] = {}
        self._markers: dict[str, str] = {}                      # job -> entry, or "~attempt" (adopted)
        self._beats: dict[tuple[str, str], float] = {}          # (job, attempt) -> expiry
        self._suspects: dict[str, float] = {}
        self._ids = itertools.count(1)
        self._changed = threading.Condition()

    def enqueue(self, job_id: str, *, unless_alive: str | None = None, owner: str = "") -> bool:
        with self._changed:
            if job_id in self._markers or (unless_alive and self._alive(job_id, unless_alive)):
                return False
            entry = str(next(self._ids))
            self._waiting.setdefault(owner, deque()).append((job_id, entry, 0))
            self._markers[job_id] = entry
            self._changed.notify()
            return True

    def withdraw(self, job_id: str, owner: str = "") -> bool:
        with self._changed:
            jobs = self._waiting.get(owner, deque())
            kept = deque(waiting for waiting in jobs if waiting[0] != job_id)
            if len(kept) == len(jobs):
                return False
            if kept:
                self._waiting[owner] = kept
            else:
                del self._waiting[owner]
            self._markers.pop(job_id, None)
            return True

    def _add(self, job_id: str, count: int = 0) -> None:
        """Hand a job back: it goes ahead of every waiting one."""
        entry = str(next(self._ids))
        self._ready.append((job_id, entry, count))
        self._markers[job_id] = entry
        self._changed.notify()

    def _next_waiting(self) -> tuple[str, str, int] | None:
        if self._ready:
            return self._ready.popleft()
        if not self._waiting:
            return None
        cap = self.running_per_owner
        open_ = [o for o in self._waiting if not cap or len(self._running[o]) < cap]
        if not open_:
            return None
        owner = min(open_, key=lambda o: (self._served.get(o, 0), o))
        jobs = self._waiting[owner]
        got = jobs.popleft()
        if not jobs:
            del self._waiting[owner]
        self._served[owner] = next(self._turns)
        self._running[owner].add(got[0])
        self._job_owner[got[0]] = owner
        return got

    def lease(self, consumer: str, block_seconds: float) -> Lease | None:
        deadline = time.monotonic() + max(0.01, block_seconds)
        with self._changed:
            while True:
                now = time.monotonic()
                for entry, held in self._leased.items():       # takeover of a silent delivery
                    if now - held.renewed >= self.lease_seconds:
                        held.consumer, held.renewed, held.count = consumer, now, held.count + 1
                        return Lease(held.job_id, entry, held.count, consumer)
                waiting = self._next_waiting()
                if waiting is not None:
                    job_id, entry, count = waiting
                    self._leased[entry] = _Delivery(job_id, consumer, now, count + 1)
                    return Lease(job_id, entry, count + 1, consumer)
                if now >= deadline:
                    return None
                self._changed.wait(min(deadline - now, 1.0))

    def renew(self, lease: Lease, attempt: str) -> Renewal:
        with self._changed:
            held = self._leased.get(lease.entry_id)
            if held is not None and held.consumer == lease.consumer:
                held.renewed = time.monotonic()
                self._beat(lease.job_id, attempt)
                return Renewal.KEPT
            return Renewal.LOST

    def _beat(self, job_id: str, attempt: str) -> None:
        self._beats[(job_id, attempt)] = time.monotonic() + self.lease_seconds

    def _alive(self, job_id: str, attempt: str) -> bool:
        return self._beats.get((job_id, attempt), 0.0) > time.monotonic()

    def alive(self, job_id: str, attempt: str) -> bool:
        with self._changed:
            return self._alive(job_id, attempt)

    def _release(self, lease: Lease, attempt: str | None) -> bool:
        held = self._leased.get(lease.entry_id)
        if held is None or held.consumer != lease.consumer:
            return False
        del self._leased[lease.entry_id]
        owner = self._job_owner.pop(lease.job_id, None)
        if owner is not None:
            self._running[owner].discard(lease.job_id)
            self._changed.notify_all()
        if self._markers.get(lease.job_id) == lease.entry_id:
            del self._markers[lease.job_id]
        if attempt:
            self._beats.pop((lease.job_id, attempt), None)
        return True

    def ack(self, lease: Lease, attempt: str | None = None) -> bool:
        with self._changed:
            return self._release(lease, attempt)

    def requeue(self, lease: Lease, attempt: str | None = None) -> bool:
        with self._changed:
            if not self._release(lease, attempt):
                return False
            if lease.job_id not in self._markers:
                self._add(lease.job_id)
            return True

    def depth(self) -> dict[str, int]:
        with self._changed:
            waiting = len(self._ready) + sum(len(jobs) for jobs in self._waiting.values())
            return {"waiting": waiting, "leased": len(self._leased)}

    def queued_ids(self) -> set[str]:
        with self._changed:
            return set(self._markers)

    def running(self, owner: str) -> int:
        with self._changed:
            return len(self._running.get(owner, ()))

    @contextmanager
    def hold(self, name: str, seconds: float = 60.0, wait: float = 30.0) -> Iterator[None]:
        with self._changed:
            lock = self._locks[name]
        if not lock.acquire(timeout=wait):
            raise LockBusy(name)
        try:
            yield
        finally:
            lock.release()

    def orphans(self, candidates: Iterable[str], grace_seconds: float) -> set[str]:
        now = time.monotonic()
        with self._changed:
            current = set(candidates)
            self._suspects = {job: self._suspects.get(job, now) for job in current}
            return {job for job, since in self._suspects.items() if now - since >= grace_seconds}


class LocalEventBus(EventBus):
    def __init__(self, keep: int = 10000):
        self._last: dict[str, int] = {}
        self._changed = threading.Condition()
        self._waiters: dict[str, set[tuple[asyncio.AbstractEventLoop, asyncio.Future]]] = defaultdict(set)

    def publish(self, job_id: str, event: dict) -> None:
        with self._changed:
            self._last[job_id] = max(self._last.get(job_id, 0), int(event["seq"]))
            self._changed.notify_all()
            waiters = self._waiters.pop(job_id, set())
        for loop, future in waiters:
            with contextlib.suppress(RuntimeError):  # that loop is closed: nobody waits there any more
                loop.call_soon_threadsafe(_resolve, future)

    def wait(self, job_id: str, after_seq: int, timeout: float) -> bool:
        with self._changed:
            return self._changed.wait_for(lambda: self._last.get(job_id, 0) > after_seq, timeout)

    async def wait_async(self, job_id: str, after_seq: int, timeout: float) -> bool:
        loop = asyncio.get_running_loop()
        future: asyncio.Future = loop.create_future()
        with self._changed:
            if self._last.get(job_id, 0) > after_seq:
                return True
            self._waiters[job_id].add((loop, future))
        try:
            await asyncio.wait_for(future, timeout)
            return True
        except TimeoutError:
            return False
        finally:
            with self._changed:
                self._waiters.get(job_id, set()).discard((loop, future))


def _resolve(future: asyncio.Future) -> None:
    if not future.done():
        future.set_result(True)


class LocalStreamSlots(StreamSlots):
    """Open streams per key in this process (the embedded mode serves from one process)."""

    def __init__(self):
        self._open: dict[str, set[str]] = defaultdict(set)
        self._lock = threading.Lock()

    async def acquire(self, owner: str, cap: int) -> str | None:
        with self._lock:
            if len(self._open[owner]) >= cap:
                return None
            slot = uuid.uuid4().hex
            self._open[owner].add(slot)
            return slot

    async def refresh(self, owner: str, slot: str) -> None:
        return None

    async def release(self, owner: str, slot: str) -> None:
        with self._lock:
            self._open[owner].discard(slot)

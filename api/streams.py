"""Fan-out of job events to the SSE clients of this API process: one feed per job, not per client.

A feed is one asyncio task per job with at least one open stream: it waits on the event bus
(:meth:`services.queue.base.EventBus.wait_async`: an async Redis ``XREAD BLOCK``, or an asyncio
future fed by the embedded workers, no thread held), reads what the store's event log gained since
its cursor (one read per job and wake-up, off the event loop, in a small limiter of its own), and
puts each event in every subscriber's queue. 200 clients on one job cost one Redis wait and one
store read per event, not 200. The store stays the source of truth: a subscriber replays what it
missed from the store itself, then takes the feed's events with a higher ``seq``.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio

from api.problems import ProblemError
from schemas.records import FINISHED
from services.jobs.service import Caller
from services.queue.base import SlotsUnavailable
from services.runtime import Runtime

log = logging.getLogger(__name__)

#: How long a feed waits on the bus before it re-reads the store anyway (the bus may have lost an
#: announcement: Redis restarted), and how often idle streams get a keep-alive comment.
WAKE_SECONDS = 15.0
#: Store reads of the feeds at once (each is one small read of a job's event log).
STORE_READERS = 8

END = None  # put in the subscribers' queues when the job's final event was sent
#: ``Retry-After`` of a stream refused for the cap (429) or because the count cannot be read (503).
RETRY_SECONDS = 5
#: The owner id :func:`api.deps.reader_of` gives a read-token caller: ``token:<resource id>``.
TOKEN_OWNER = "token:"


def finishes(event: dict) -> bool:
    return event.get("type") == "status" and event.get("status") in FINISHED


def counted_owner(caller: Caller, resource_owner: str) -> str:
    """The key a stream counts against. A bearer caller's own; a read-token caller's is the owner
    of the resource the token reads: tokens are only minted for the resource's owner (or an admin,
    whose reads of a tenant's resource then count against that tenant), so a key cannot multiply its
    streams by opening them with tokens of its jobs and experiments."""
    return resource_owner if caller.owner.startswith(TOKEN_OWNER) else caller.owner


class StreamSlot:
    """One open stream's place under its key's cap (``NDRF_MAX_STREAMS_PER_KEY``), counted across
    every API process (:class:`services.queue.base.StreamSlots`). Guards the cap: over it the stream
    is refused with 429; when the count cannot be read (Redis away or busy) with 503, never let in
    uncounted. Both carry ``Retry-After``."""

    def __init__(self, runtime: Runtime, owner: str, slot: str):
        self.runtime, self.owner, self.slot = runtime, owner, slot
        self.refreshed = time.monotonic()

    @classmethod
    async def take(cls, runtime: Runtime, owner: str, what: str = "event streams") -> StreamSlot:
        slots, cap = runtime.slots, runtime.settings.limits.streams_per_key
        assert slots is not None
        retry = {"Retry-After": str(RETRY_SECONDS)}
        try:
            slot = await slots.acquire(owner, cap)
        except SlotsUnavailable:
            raise ProblemError(503, "Streams unavailable", "the count of open streams cannot be checked now; "
                                                           "try again shortly", slug="streams-unavailable",
                               headers=retry) from None
        if slot is None:
            raise ProblemError(429, "Too many streams", f"this key already holds {cap} {what} "
                                                        f"(NDRF_MAX_STREAMS_PER_KEY)", slug="too-many-streams",
                               headers=retry)
        return cls(runtime, owner, slot)

    async def keep(self) -> None:
        """Refresh the slot if a third of its lifetime passed (call on every event or keep-alive)."""
        slots = self.runtime.slots
        assert slots is not None
        if time.monotonic() - self.refreshed > slots.ttl_seconds / 3:
            self.refreshed = time.monotonic()
            await slots.refresh(self.owner, self.slot)

    async def release(self) -> None:
        slots = self.runtime.slots
        assert slots is not None
        with anyio.CancelScope(shield=True):
            await slots.release(self.owner, self.slot)


class _Feed:
    def __init__(self):
        self.subscribers: set[asyncio.Queue] = set()
        self.task: asyncio.Task | None = None
        self.seq = 0
        self.cursor = None


class StreamHub:
    def __init__(self, runtime: Runtime, wake_seconds: float = WAKE_SECONDS):
        self.runtime = runtime
        self.wake_seconds = wake_seconds
        self.feeds: dict[str, _Feed] = {}
        self.limiter = anyio.CapacityLimiter(STORE_READERS)

    async def blocking(self, fn, *args):
        """Run a store read off the event loop (its own limiter: never queued behind preflight)."""
        return await anyio.to_thread.run_sync(fn, *args, limiter=self.limiter)

    async def finished(self, job_id: str) -> bool:
        record = await self.blocking(self.runtime.service.states.get, job_id)
        return record.status in FINISHED

    async def replay(self, job_id: str, after: int) -> list[dict]:
        files = self.runtime.service.states.files(job_id)
        events, _ = await self.blocking(files.store.read_events, files.prefix, after, None)
        return events

    @asynccontextmanager
    async def subscribe(self, job_id: str) -> AsyncIterator[asyncio.Queue]:
        """A queue of the job's events read from now on (``END`` after the final one)."""
        feed = self.feeds.get(job_id)
        if feed is None or feed.task is None or feed.task.done():
            feed = self.feeds[job_id] = _Feed()
            feed.task = asyncio.create_task(self._run(job_id, feed), name=f"feed-{job_id}")
        queue: asyncio.Queue = asyncio.Queue()
        feed.subscribers.add(queue)
        try:
            yield queue
        finally:
            feed.subscribers.discard(queue)
            if not feed.subscribers and feed.task is not None:
                feed.task.cancel()
                if self.feeds.get(job_id) is feed:
                    del self.feeds[job_id]

    async def _run(self, job_id: str, feed: _Feed) -> None:
        files = self.runtime.service.states.files(job_id)
        try:
            while True:
                try:
                    events, feed.cursor = await self.blocking(files.store.read_events, files.prefix, feed.seq,
                                                              feed.cursor)
                except Exception as exc:  # the store is briefly away: try again at the next wake-up
                    log.warning("event feed of job %s: store read failed: %s", job_id, exc)
                    events = []
                for event in events:
                    feed.seq = max(feed.seq, int(event.get("seq", 0)))
                    for queue in feed.subscribers:
                        queue.put_nowait(event)
                if any(finishes(e) for e in events) and await self.finished(job_id):
                    for queue in feed.subscribers:
                        queue.put_nowait(END)
                    return
                await self.runtime.events.wait_async(job_id, feed.seq, self.wake_seconds)
        except Exception:  # the job was deleted, or a bug: end its streams rather than leave them hanging
            log.exception("event feed of job %s failed", job_id)
            for queue in feed.subscribers:
                queue.put_nowait(END)
        finally:
            if self.feeds.get(job_id) is feed:
                del self.feeds[job_id]

    async def close(self) -> None:
        for feed in list(self.feeds.values()):
            if feed.task is not None:
                feed.task.cancel()
        self.feeds.clear()

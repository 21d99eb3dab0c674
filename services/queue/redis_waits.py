"""The Redis connections of an API process's event loop: a bounded pool for commands, and one
connection of its own for every stream wait.

Before, each event stream held a pooled connection for an ``XREAD BLOCK`` of up to 15 s: one tenant
opening many streams took the pool (and with it the stream slots, the reads of other tenants'
streams and every other route that talks to Redis). Here:

* :func:`command_client` is the client for short commands (stream slots, ``XREVRANGE``): a
  :class:`redis.asyncio.BlockingConnectionPool` of ``NDRF_REDIS_CONNECTIONS`` connections. A
  command that finds them all busy for ``POOL_WAIT_SECONDS`` fails (a stream is then refused with
  503, never let in uncapped); no command ever blocks on the server.
* :class:`StreamWaits` waits on *every* stream the process's readers wait on with one
  ``XREAD BLOCK`` over all of them, on a pool of two connections of its own (the wait, and the
  wake-up sent when a new stream joins). However many streams a tenant opens, it costs one more
  key in that one read: it cannot starve another tenant's streams, nor the other routes.
"""

from __future__ import annotations

import asyncio
import logging
import time
import uuid
from typing import Any

import redis
import redis.asyncio

log = logging.getLogger(__name__)

#: How long a command waits for a free connection of the pool before it fails.
POOL_WAIT_SECONDS = 1.0
#: The longest ``XREAD BLOCK`` of the multiplexed wait (a stream whose wake-up failed waits at most
#: this long before it is in the read; it misses nothing: the read starts after its last id).
BLOCK_SECONDS = 5.0
WAKE = "ndrf:wake:{}"
REDIS_ERRORS = (redis.RedisError, OSError, TimeoutError)


def command_client(url: str, connections: int) -> redis.asyncio.Redis:
    """The event loop's client for short commands: at most ``connections`` connections; a command
    that finds none free within ``POOL_WAIT_SECONDS`` raises :class:`redis.ConnectionError`."""
    pool = redis.asyncio.BlockingConnectionPool.from_url(
        url, max_connections=connections, timeout=POOL_WAIT_SECONDS, decode_responses=True,
        socket_connect_timeout=5, socket_timeout=10, health_check_interval=15)
    return redis.asyncio.Redis(connection_pool=pool)


class Quiet:
    """A warning logged at most once per ``seconds`` (with how many were left out): a Redis that is
    away must not write thousands of lines a minute."""

    def __init__(self, seconds: float = 30.0):
        self.seconds, self.last, self.dropped = seconds, float("-inf"), 0

    def warning(self, message: str, *args: Any) -> None:
        now = time.monotonic()
        if now - self.last < self.seconds:
            self.dropped += 1
            return
        suffix = f" ({self.dropped} more like it not logged)" if self.dropped else ""
        log.warning(message + suffix, *args)
        self.last, self.dropped = now, 0


class StreamWaits:
    """Every stream wait of one event loop, multiplexed on one ``XREAD BLOCK``.

    A waiter names a stream and the last entry id it has seen; the read runs while there is a
    waiter, over all their streams plus a private wake-up stream (``ndrf:wake:<uuid>``), to which a
    waiter on a stream not yet in the read adds an entry so that the read restarts with it. New
    entries in a stream wake all its waiters (they then read the store, the source of truth). If
    Redis fails, every waiter is woken (they re-read the store) and the read is retried after a
    second: readers fall back to polling the store, never to spinning.
    """

    def __init__(self, url: str, block_seconds: float = BLOCK_SECONDS):
        pool = redis.asyncio.BlockingConnectionPool.from_url(
            url, max_connections=2, timeout=5, decode_responses=True, socket_connect_timeout=5,
            socket_timeout=block_seconds + 10, health_check_interval=15)
        self.client = redis.asyncio.Redis(connection_pool=pool)
        self.block_seconds = block_seconds
        self.wake = WAKE.format(uuid.uuid4().hex)
        self.wake_id = "0-0"  # a private stream: from its start, so that no wake-up is ever missed
        self.waiters: dict[str, set[asyncio.Future]] = {}
        self.ids: dict[str, str] = {}
        self.task: asyncio.Task | None = None
        self.quiet = Quiet()

    async def wait(self, stream: str, last_id: str, timeout: float) -> bool:
        """Until ``stream`` has an entry after ``last_id`` (True), or ``timeout`` seconds (False)."""
        future: asyncio.Future = asyncio.get_running_loop().create_future()
        joined = stream not in self.waiters
        self.waiters.setdefault(stream, set()).add(future)
        if joined:
            self.ids[stream] = last_id
        if self.task is None or self.task.done():
            self.task = asyncio.create_task(self._run(), name="redis-stream-waits")
        elif joined:
            await self._poke()
        try:
            return await asyncio.wait_for(asyncio.shield(future), timeout)
        except TimeoutError:
            return False
        finally:
            held = self.waiters.get(stream)
            if held is not None:
                held.discard(future)
                if not held:
                    del self.waiters[stream]
                    self.ids.pop(stream, None)

    async def _poke(self) -> None:
        try:
            async with self.client.pipeline(transaction=False) as pipe:
                pipe.xadd(self.wake, {"w": "1"}, maxlen=1)
                pipe.pexpire(self.wake, int((self.block_seconds + 60) * 1000))
                await asyncio.wait_for(pipe.execute(), 5)
        except REDIS_ERRORS as exc:  # the stream joins at the next turn of the read (<= BLOCK_SECONDS)
            self.quiet.warning("stream wait wake-up failed: %s", exc)

    def _wake(self, stream: str) -> None:
        for future in self.waiters.pop(stream, set()):
            if not future.done():
                future.set_result(True)
        self.ids.pop(stream, None)

    async def _run(self) -> None:
        while self.waiters:
            streams: dict[Any, Any] = {self.wake: self.wake_id, **self.ids}
            try:
                reply = await asyncio.wait_for(self.client.xread(streams, block=int(self.block_seconds * 1000)),
                                               self.block_seconds + 10)
            except REDIS_ERRORS as exc:
                self.quiet.warning("event streams unavailable, readers poll the store: %s", exc)
                for stream in list(self.waiters):
                    self._wake(stream)
                await asyncio.sleep(1.0)
                continue
            for stream, entries in _streams(reply):
                if stream == self.wake and entries:
                    self.wake_id = str(entries[-1][0])
                elif entries:
                    self._wake(stream)

    async def aclose(self) -> None:
        if self.task is not None:
            self.task.cancel()
            await asyncio.gather(self.task, return_exceptions=True)
        for stream in list(self.waiters):
            self._wake(stream)
        await self.client.aclose()


def _streams(reply: Any) -> list[tuple[str, list]]:
    """The (stream, entries) pairs of an XREAD reply (RESP2 list or RESP3 dict)."""
    if not reply:
        return []
    if isinstance(reply, dict):
        return [(str(stream), list(entries or [])) for stream, entries in reply.items()]
    return [(str(stream), list(entries or [])) for stream, entries in reply]

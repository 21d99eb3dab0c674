"""Redis Streams queue: one stream of job ids, one consumer group of workers, and a few keys.

    ndrf:jobs                      stream of entries ``job <id>``, consumer group ``workers``
    ndrf:queued                    hash job -> its one entry id, or ``~<attempt>`` (adopted, see below;
                                   such a marker holds the job only while that attempt's heartbeat lives)
    ndrf:alive:<job>:<attempt>     heartbeat of a running attempt (value: consumer; PX = the lease)
    ndrf:orphans                   hash job -> when the reconciler first missed it (Redis TIME, ms)

    enqueue    Lua: no-op if the job has a marker (or the named attempt is alive); else the job joins
               its owner's waiting list (marker ``w``): :mod:`services.queue.redis_fair`
    lease      XAUTOCLAIM entries idle >= lease (their owner stopped renewing), else Lua: an unread
               entry of the stream, else the least recently served owner's next job moved into the
               stream and read (XREADGROUP), in one step; idle workers block on ``ndrf:wake``
    renew      Lua: if XPENDING names this consumer as the entry's owner: XCLAIM JUSTID (idle = 0) and
               refresh the heartbeat; owned by another consumer: lost; not pending at all and the job
               has no marker (Redis restarted empty): adopt (marker ``~<attempt>`` + heartbeat)
    ack        Lua: XACK + XDEL + drop the marker only if this consumer still owns the entry (or its
               adopted marker): a fenced attempt never removes its successor's delivery
    requeue    Lua: ack as above, then XADD a new entry and point the marker at it, in one step

Idle time and heartbeat are reset in the same script, so "idle for a lease period" (XAUTOCLAIM's
test) and "heartbeat expired" agree. The delivery counter Redis keeps per pending entry is the
delivery number. Events go to a stream per job, ``ndrf:events:<id>``, trimmed (the store keeps
them all); waiting on it uses ``redis.asyncio`` on the event loop (no thread held), with connections
of its own (:mod:`services.queue.redis_waits`).
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
import uuid
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from typing import Any

import redis
import redis.asyncio

from services.queue import redis_fair as fair
from services.queue.base import EventBus, JobQueue, Lease, LockBusy, Renewal, SlotsUnavailable, StreamSlots
from services.queue.redis_waits import REDIS_ERRORS, Quiet, StreamWaits, command_client

log = logging.getLogger(__name__)

STREAM = "ndrf:jobs"
GROUP = "workers"
MARKERS = "ndrf:queued"
BEAT = "ndrf:alive:{}:{}"
ORPHANS = "ndrf:orphans"
EVENTS = "ndrf:events:{}"
SLOTS = "ndrf:streams:{}"
EVENTS_MAXLEN = 10000

# The owner of one pending entry: ``p`` is XPENDING's reply ({} when not pending or no group).
_OWNER = """
local p = redis.pcall('XPENDING', KEYS[1], ARGV[1], ARGV[3], ARGV[3], 1)
if type(p) ~= 'table' or p.err or #p == 0 then p = nil end
"""

# An adopted marker (``~<attempt>``) holds the job only while that attempt's heartbeat lives: the
# adopting worker may die too, and then nothing else would ever bring the job back.
_STALE = """
local function stale(job, m)
  return string.sub(m, 1, 1) == '~' and redis.call('EXISTS', 'ndrf:alive:' .. job .. ':' .. string.sub(m, 2)) == 0
end
"""

# KEYS stream, markers, beat   ARGV group, consumer, entry, lease ms, job, attempt
_RENEW = _OWNER + """
if p then
  if p[1][2] ~= ARGV[2] then return 0 end
  redis.call('XCLAIM', KEYS[1], ARGV[1], ARGV[2], 0, ARGV[3], 'JUSTID')
  redis.call('SET', KEYS[3], ARGV[2], 'PX', ARGV[4])
  return 1
end
local m = redis.call('HGET', KEYS[2], ARGV[5])
if m == '~' .. ARGV[6] then
  redis.call('SET', KEYS[3], ARGV[2], 'PX', ARGV[4])
  return 1
end
if m then return 0 end
redis.call('HSET', KEYS[2], ARGV[5], '~' .. ARGV[6])
redis.call('SET', KEYS[3], ARGV[2], 'PX', ARGV[4])
return 2
"""

# KEYS stream, markers, beat   ARGV group, consumer, entry, job, attempt, requeue (1/0)
_RELEASE = _OWNER + "local function release_running()\n" + fair.RELEASE_RUNNING + "end\n" + """
local mine = 0
local m = redis.call('HGET', KEYS[2], ARGV[4])
if p then
  if p[1][2] == ARGV[2] then
    redis.call('XACK', KEYS[1], ARGV[1], ARGV[3])
    redis.call('XDEL', KEYS[1], ARGV[3])
    if m == ARGV[3] then redis.call('HDEL', KEYS[2], ARGV[4]); m = false end
    mine = 1
  end
elseif ARGV[5] ~= '' and m == '~' .. ARGV[5] then
  redis.call('HDEL', KEYS[2], ARGV[4]); m = false
  mine = 1
end
if KEYS[3] ~= '' then redis.call('DEL', KEYS[3]) end
if mine == 1 then release_running() end
if mine == 1 and ARGV[6] == '1' and not m then
  redis.pcall('XGROUP', 'CREATE', KEYS[1], ARGV[1], '0', 'MKSTREAM')
  local id = redis.call('XADD', KEYS[1], '*', 'job', ARGV[4])
  redis.call('HSET', KEYS[2], ARGV[4], id)
  redis.call('RPUSH', 'ndrf:wake', '1')
  redis.call('LTRIM', 'ndrf:wake', -16, -1)
end
return mine
"""

# KEYS markers: the jobs held by a live marker
_HELD = _STALE + """
local out = {}
local all = redis.call('HGETALL', KEYS[1])
for i = 1, #all, 2 do
  if not stale(all[i], all[i + 1]) then table.insert(out, all[i]) end
end
return out
"""

# KEYS orphans   ARGV grace ms, candidates...
_ORPHANS = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
local keep = {}
for i = 2, #ARGV do keep[ARGV[i]] = true end
local known = redis.call('HKEYS', KEYS[1])
for _, job in ipairs(known) do
  if not keep[job] then redis.call('HDEL', KEYS[1], job) end
end
local due = {}
for i = 2, #ARGV do
  local since = redis.call('HGET', KEYS[1], ARGV[i])
  if not since then
    redis.call('HSET', KEYS[1], ARGV[i], now)
  elseif now - tonumber(since) >= tonumber(ARGV[1]) then
    table.insert(due, ARGV[i])
  end
end
return due
"""

# KEYS slots of one owner   ARGV cap, ttl ms, slot
_ACQUIRE = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
redis.call('ZREMRANGEBYSCORE', KEYS[1], '-inf', now)
if redis.call('ZCARD', KEYS[1]) >= tonumber(ARGV[1]) then return 0 end
redis.call('ZADD', KEYS[1], now + tonumber(ARGV[2]), ARGV[3])
redis.call('PEXPIRE', KEYS[1], ARGV[2])
return 1
"""

_REFRESH = """
local t = redis.call('TIME')
local now = tonumber(t[1]) * 1000 + math.floor(tonumber(t[2]) / 1000)
redis.call('ZADD', KEYS[1], 'XX', now + tonumber(ARGV[1]), ARGV[2])
redis.call('PEXPIRE', KEYS[1], ARGV[1])
return 1
"""


#: A stream entry as a client with ``decode_responses=True`` returns it: (id, fields).
Entry = tuple[str, dict[str, str]]


def _entries(raw: Any) -> list[Entry]:
    """The entries of an XRANGE/XREVRANGE/XAUTOCLAIM list. redis-py types every reply as a union
    of bytes, str and None whatever ``decode_responses`` says; the clients here decode, so ids and
    fields are str (a deleted entry's fields are None: returned as an empty dict)."""
    return [(str(entry_id), dict(fields or {})) for entry_id, fields in raw or []]


def _read_entries(reply: Any) -> list[Entry]:
    """The entries of the first stream in an XREAD/XREADGROUP reply (RESP2: ``[[stream, entries]]``)."""
    return _entries(reply[0][1]) if reply else []


def connect(url: str) -> redis.Redis:
    return redis.Redis.from_url(url, decode_responses=True, socket_timeout=30, socket_connect_timeout=5,
                                health_check_interval=15)


class RedisJobQueue(JobQueue):
    def __init__(self, client: redis.Redis, lease_seconds: float, running_per_owner: int = 0):
        self.redis = client
        self.running_per_owner = running_per_owner
        self.lease_seconds = lease_seconds
        self.lease_ms = int(lease_seconds * 1000)
        self._enqueue = client.register_script(fair.ENQUEUE)
        self._dispatch = client.register_script(fair.DISPATCH)
        self._waiting = client.register_script(fair.WAITING)
        self._withdraw = client.register_script(fair.WITHDRAW)
        self._unlock = client.register_script(fair.UNLOCK)
        self._renew = client.register_script(_RENEW)
        self._release = client.register_script(_RELEASE)
        self._orphans = client.register_script(_ORPHANS)
        self._held = client.register_script(_HELD)
        self._ensure_group()

    def _ensure_group(self) -> None:
        try:
            self.redis.xgroup_create(STREAM, GROUP, id="0", mkstream=True)
        except redis.ResponseError as exc:
            if "BUSYGROUP" not in str(exc):
                raise

    def _retrying(self, fn):
        """Run ``fn``; if Redis lost the group (a restart without persistence), recreate it once."""
        try:
            return fn()
        except redis.ResponseError as exc:
            if "NOGROUP" not in str(exc):
                raise
            self._ensure_group()
            return fn()

    def enqueue(self, job_id: str, *, unless_alive: str | None = None, owner: str = "") -> bool:
        beat = BEAT.format(job_id, unless_alive) if unless_alive else ""
        return self._enqueue(keys=[STREAM, MARKERS, beat, fair.OWNERS, fair.SERVED, fair.WAKE],
                             args=[job_id, GROUP, owner]) is not None

    def withdraw(self, job_id: str, owner: str = "") -> bool:
        return bool(self._withdraw(keys=[MARKERS, fair.OWNERS], args=[job_id, owner]))

    def _dispatched(self, consumer: str) -> list[Entry]:
        reply = self._dispatch(keys=[STREAM, MARKERS, fair.OWNERS, fair.SERVED, fair.TURN],
                               args=[GROUP, consumer, self.running_per_owner])
        # a script's XREADGROUP reply is raw: [[stream, [[id, [field, value, ...]]]]]
        entries = reply[0][1] if reply else []
        return [(str(entry_id), dict(zip(flat[::2], flat[1::2]))) for entry_id, flat in entries]

    @contextmanager
    def hold(self, name: str, seconds: float = 60.0, wait: float = 30.0) -> Iterator[None]:
        key, token = fair.LOCK.format(name), uuid.uuid4().hex
        deadline = time.monotonic() + wait
        while not self.redis.set(key, token, nx=True, px=int(seconds * 1000)):
            if time.monotonic() > deadline:
                raise LockBusy(name)
            time.sleep(0.02)
        try:
            yield
        finally:
            self._unlock(keys=[key], args=[token])

    def _delivery(self, entry_id: str) -> int:
        pending = self.redis.xpending_range(STREAM, GROUP, min=entry_id, max=entry_id, count=1)
        return int(pending[0]["times_delivered"]) if pending else 1

    def lease(self, consumer: str, block_seconds: float) -> Lease | None:
        def attempt():
            reply: Any = self.redis.xautoclaim(STREAM, GROUP, consumer, self.lease_ms, "0-0", count=1)
            claimed = _entries(reply[1])
            if claimed:
                entry_id, fields = claimed[0]
                if not fields:  # the entry was deleted meanwhile
                    self.redis.xack(STREAM, GROUP, entry_id)
                    return None
                log.warning("took over job %s (entry %s) from a consumer that stopped renewing", fields["job"],
                            entry_id)
                return Lease(fields["job"], entry_id, self._delivery(entry_id), consumer)
            read = self._dispatched(consumer)
            if not read:
                self.redis.blpop([fair.WAKE], timeout=max(0.01, block_seconds))
                read = self._dispatched(consumer)
            if not read:
                return None
            entry_id, fields = read[0]
            return Lease(fields["job"], entry_id, self._delivery(entry_id), consumer)

        return self._retrying(attempt)

    def renew(self, lease: Lease, attempt: str) -> Renewal:
        got = self._renew(keys=[STREAM, MARKERS, BEAT.format(lease.job_id, attempt)],
                          args=[GROUP, lease.consumer, lease.entry_id, self.lease_ms, lease.job_id, attempt])
        return {1: Renewal.KEPT, 2: Renewal.ADOPTED}.get(int(got), Renewal.LOST)

    def alive(self, job_id: str, attempt: str) -> bool:
        return bool(self.redis.exists(BEAT.format(job_id, attempt)))

    def _release_entry(self, lease: Lease, attempt: str | None, requeue: bool) -> bool:
        beat = BEAT.format(lease.job_id, attempt) if attempt else ""
        return bool(self._release(keys=[STREAM, MARKERS, beat],
                                  args=[GROUP, lease.consumer, lease.entry_id, lease.job_id, attempt or "",
                                        "1" if requeue else "0"]))

    def ack(self, lease: Lease, attempt: str | None = None) -> bool:
        return self._release_entry(lease, attempt, requeue=False)

    def requeue(self, lease: Lease, attempt: str | None = None) -> bool:
        return self._release_entry(lease, attempt, requeue=True)

    def depth(self) -> dict[str, int]:
        waiting = int(self._waiting(keys=[fair.OWNERS]))
        try:
            groups = {g["name"]: g for g in self.redis.xinfo_groups(STREAM)}
        except redis.ResponseError:
            return {"waiting": waiting, "leased": 0}
        group = groups.get(GROUP, {})
        return {"waiting": waiting + int(group.get("lag") or 0), "leased": int(group.get("pending") or 0)}

    def queued_ids(self) -> set[str]:
        return set(self._held(keys=[MARKERS]))

    def running(self, owner: str) -> int:
        return int(self.redis.scard(fair.RUNNING + owner))

    def orphans(self, candidates: Iterable[str], grace_seconds: float) -> set[str]:
        jobs = sorted(set(candidates))
        if not jobs:
            self.redis.delete(ORPHANS)
            return set()
        return set(self._orphans(keys=[ORPHANS], args=[int(grace_seconds * 1000), *jobs]))


class RedisEventBus(EventBus):
    """Events on ``ndrf:events:<job>``; threads wait with the blocking client, the event loop with
    clients of its own (made on first use, per loop, :mod:`services.queue.redis_waits`): a bounded
    pool for short commands, and one multiplexed ``XREAD BLOCK`` for every wait."""

    def __init__(self, client: redis.Redis, url: str | None = None, connections: int = 32):
        self.redis = client
        self.url = url
        self.connections = connections
        self._async: tuple[asyncio.AbstractEventLoop, redis.asyncio.Redis, StreamWaits] | None = None
        self.quiet = Quiet()

    def publish(self, job_id: str, event: dict) -> None:
        try:
            self.redis.xadd(EVENTS.format(job_id), {"seq": event["seq"], "data": json.dumps(event)},
                            maxlen=EVENTS_MAXLEN, approximate=True)
        except redis.RedisError as exc:  # the store has the event; live push is best effort
            log.warning("could not publish event %s of job %s: %s", event.get("seq"), job_id, exc)

    def wait(self, job_id: str, after_seq: int, timeout: float) -> bool:
        stream = EVENTS.format(job_id)
        try:
            last = _entries(self.redis.xrevrange(stream, count=1))
            if last and int(last[0][1]["seq"]) > after_seq:
                return True
            reply = self.redis.xread({stream: last[0][0] if last else "0-0"}, count=1,
                                     block=max(1, int(timeout * 1000)))
            return bool(reply)
        except redis.RedisError as exc:  # Redis away: readers fall back to the store, a bit later
            log.warning("event stream of job %s unavailable: %s", job_id, exc)
            time.sleep(min(timeout, 1.0))
            return True

    def _loop_clients(self) -> tuple[redis.asyncio.Redis, StreamWaits]:
        loop = asyncio.get_running_loop()
        if self._async is None or self._async[0] is not loop:
            if self.url is None:
                raise RuntimeError("RedisEventBus needs the Redis URL to wait on the event loop")
            self._async = (loop, command_client(self.url, self.connections), StreamWaits(self.url))
        return self._async[1], self._async[2]

    def async_client(self) -> redis.asyncio.Redis:
        """The event loop's client for short commands (a bounded pool; never an ``XREAD BLOCK``)."""
        return self._loop_clients()[0]

    async def wait_async(self, job_id: str, after_seq: int, timeout: float) -> bool:
        stream = EVENTS.format(job_id)
        client, waits = self._loop_clients()
        try:
            last = _entries(await asyncio.wait_for(client.xrevrange(stream, count=1), 10))
        except REDIS_ERRORS as exc:  # Redis away or busy: readers re-read the store
            self.quiet.warning("event stream of job %s unavailable: %s", job_id, exc)
            await asyncio.sleep(min(timeout, 1.0))
            return True
        if last and int(last[0][1]["seq"]) > after_seq:
            return True
        return await waits.wait(stream, last[0][0] if last else "0-0", timeout)

    async def aclose(self) -> None:
        if self._async is not None:
            _, client, waits = self._async
            self._async = None
            await waits.aclose()
            await client.aclose()


class RedisStreamSlots(StreamSlots):
    """``ndrf:streams:<owner>``: a sorted set of open streams, scored by when each expires, shared by
    every API process (a process that dies leaves slots that expire after ``ttl_seconds``).

    Guards the per-key stream cap. It fails closed: when Redis cannot answer (away, or the command
    pool busy for ``POOL_WAIT_SECONDS``) :meth:`acquire` raises :class:`SlotsUnavailable` (the
    route answers 503 with ``Retry-After``); it never lets a stream in uncounted."""

    def __init__(self, bus: RedisEventBus, ttl_seconds: float = 60.0):
        self.bus, self.ttl_seconds = bus, ttl_seconds
        self.quiet = Quiet()

    async def acquire(self, owner: str, cap: int) -> str | None:
        slot = uuid.uuid4().hex
        try:
            got = await asyncio.wait_for(self.bus.async_client().eval(
                _ACQUIRE, 1, SLOTS.format(owner), cap, int(self.ttl_seconds * 1000), slot), 5)
        except REDIS_ERRORS as exc:
            self.quiet.warning("stream slots unavailable, refusing streams: %s", exc)
            raise SlotsUnavailable(str(exc)) from None
        return slot if int(got) else None

    async def refresh(self, owner: str, slot: str) -> None:
        try:
            await asyncio.wait_for(self.bus.async_client().eval(
                _REFRESH, 1, SLOTS.format(owner), int(self.ttl_seconds * 1000), slot), 5)
        except REDIS_ERRORS as exc:
            self.quiet.warning("stream slot refresh failed: %s", exc)

    async def release(self, owner: str, slot: str) -> None:
        try:
            await asyncio.wait_for(self.bus.async_client().zrem(SLOTS.format(owner), slot), 5)
        except REDIS_ERRORS as exc:  # it expires by itself
            self.quiet.warning("stream slot release failed: %s", exc)

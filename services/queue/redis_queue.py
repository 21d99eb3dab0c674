"""Redis Streams queue: one stream of job ids, one consumer group of workers.

    XADD       ndrf:jobs * job <id>                         enqueue
    XAUTOCLAIM ndrf:jobs workers <me> <lease ms> 0-0 COUNT 1  take over an entry whose worker
                                                               stopped renewing (dead or hung)
    XREADGROUP GROUP workers <me> COUNT 1 BLOCK <ms> STREAMS ndrf:jobs >    a new entry
    XCLAIM     ndrf:jobs workers <me> 0 <entry> JUSTID      renew: reset the entry's idle time
    XACK + XDEL                                             done

The delivery counter Redis keeps per pending entry is the attempt number. Events go to a stream
per job, ``ndrf:events:<id>``, trimmed to the most recent entries (the store keeps them all).
"""

from __future__ import annotations

import json
import logging
import time

import redis

from services.queue.base import EventBus, JobQueue, Lease

log = logging.getLogger(__name__)

STREAM = "ndrf:jobs"
GROUP = "workers"
EVENTS = "ndrf:events:{}"
EVENTS_MAXLEN = 10000


def connect(url: str) -> redis.Redis:
    return redis.Redis.from_url(url, decode_responses=True, socket_timeout=30, socket_connect_timeout=5,
                                health_check_interval=15)


class RedisJobQueue(JobQueue):
    def __init__(self, client: redis.Redis, lease_seconds: float):
        self.redis = client
        self.lease_ms = int(lease_seconds * 1000)
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

    def enqueue(self, job_id: str) -> None:
        self._retrying(lambda: self.redis.xadd(STREAM, {"job": job_id}))

    def _delivery(self, entry_id: str) -> int:
        pending = self.redis.xpending_range(STREAM, GROUP, min=entry_id, max=entry_id, count=1)
        return int(pending[0]["times_delivered"]) if pending else 1

    def lease(self, consumer: str, block_seconds: float) -> Lease | None:
        def attempt():
            _, claimed, _ = self.redis.xautoclaim(STREAM, GROUP, consumer, self.lease_ms, "0-0", count=1)
            if claimed:
                entry_id, fields = claimed[0]
                if fields is None:  # the entry was deleted meanwhile
                    self.redis.xack(STREAM, GROUP, entry_id)
                    return None
                log.warning("took over job %s (entry %s) from a worker whose lease expired", fields["job"], entry_id)
                return Lease(fields["job"], entry_id, self._delivery(entry_id))
            reply = self.redis.xreadgroup(GROUP, consumer, {STREAM: ">"}, count=1,
                                          block=max(1, int(block_seconds * 1000)))
            if not reply:
                return None
            entry_id, fields = reply[0][1][0]
            return Lease(fields["job"], entry_id, self._delivery(entry_id))

        return self._retrying(attempt)

    def renew(self, lease: Lease, consumer: str) -> bool:
        claimed = self._retrying(lambda: self.redis.xclaim(STREAM, GROUP, consumer, 0, [lease.entry_id], justid=True))
        if not claimed:
            return False
        owner = self.redis.xpending_range(STREAM, GROUP, min=lease.entry_id, max=lease.entry_id, count=1)
        return bool(owner) and owner[0]["consumer"] == consumer

    def ack(self, lease: Lease) -> None:
        pipe = self.redis.pipeline()
        pipe.xack(STREAM, GROUP, lease.entry_id)
        pipe.xdel(STREAM, lease.entry_id)
        pipe.execute()

    def depth(self) -> dict[str, int]:
        try:
            groups = {g["name"]: g for g in self.redis.xinfo_groups(STREAM)}
        except redis.ResponseError:
            return {"waiting": 0, "leased": 0}
        group = groups.get(GROUP, {})
        return {"waiting": int(group.get("lag") or 0), "leased": int(group.get("pending") or 0)}

    def queued_ids(self) -> set[str]:
        try:
            return {fields["job"] for _, fields in self.redis.xrange(STREAM) if fields}
        except redis.ResponseError:
            return set()


class RedisEventBus(EventBus):
    def __init__(self, client: redis.Redis):
        self.redis = client

    def publish(self, job_id: str, event: dict) -> None:
        try:
            self.redis.xadd(EVENTS.format(job_id), {"seq": event["seq"], "data": json.dumps(event)},
                            maxlen=EVENTS_MAXLEN, approximate=True)
        except redis.RedisError as exc:  # the store has the event; live push is best effort
            log.warning("could not publish event %s of job %s: %s", event.get("seq"), job_id, exc)

    def wait(self, job_id: str, after_seq: int, timeout: float) -> bool:
        stream = EVENTS.format(job_id)
        try:
            last = self.redis.xrevrange(stream, count=1)
            if last and int(last[0][1]["seq"]) > after_seq:
                return True
            reply = self.redis.xread({stream: last[0][0] if last else "0-0"}, count=1,
                                     block=max(1, int(timeout * 1000)))
            return bool(reply)
        except redis.RedisError as exc:  # Redis away: readers fall back to the store, a bit later
            log.warning("event stream of job %s unavailable: %s", job_id, exc)
            time.sleep(min(timeout, 1.0))
            return True

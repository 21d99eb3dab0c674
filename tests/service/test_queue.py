"""The queue's contract (services/queue/base.py) against a real Redis server and the in-process
queue: one marker per job, heartbeats that expire, owned renewals and acks, adoption after Redis
lost its data, the reconciler's grace; the event bus's async wait; stream slots across processes."""

from __future__ import annotations

import asyncio
import time

import pytest

from harness.cluster import Redis
from services.queue.base import Renewal
from services.queue.local import LocalEventBus, LocalJobQueue, LocalStreamSlots

LEASE = 0.6


@pytest.fixture(scope="module")
def redis_server():
    server = Redis().start()
    yield server
    server.kill()


@pytest.fixture(params=["redis", "local"])
def queue(request, redis_server):
    if request.param == "local":
        return LocalJobQueue(LEASE)
    from services.queue.redis_queue import RedisJobQueue, connect

    client = connect(redis_server.url)
    client.flushall()
    return RedisJobQueue(client, LEASE)


def test_enqueue_is_a_no_op_while_the_job_is_queued_or_leased(queue):
    assert queue.enqueue("a") and not queue.enqueue("a")
    assert queue.depth()["waiting"] == 1
    lease = queue.lease("c1", 0.1)
    assert lease is not None and lease.job_id == "a" and lease.delivery == 1
    assert not queue.enqueue("a")                          # leased: still one marker
    assert queue.lease("c2", 0.1) is None
    assert queue.queued_ids() == {"a"}
    assert queue.ack(lease, "a#1")
    assert queue.queued_ids() == set() and queue.enqueue("a")


def test_heartbeat_expires_and_only_then_the_delivery_moves(queue):
    queue.enqueue("a")
    first = queue.lease("c1", 0.1)
    assert queue.renew(first, "w1#1") is Renewal.KEPT and queue.alive("a", "w1#1")
    for _ in range(3):                                      # renewed: nobody else gets it
        time.sleep(LEASE / 3)
        assert queue.renew(first, "w1#1") is Renewal.KEPT
        assert queue.lease("c2", 0.01) is None
    time.sleep(LEASE * 1.3)                                 # c1 went silent
    assert not queue.alive("a", "w1#1")
    second = queue.lease("c2", 0.1)
    assert second is not None and second.entry_id == first.entry_id and second.delivery == 2
    assert queue.renew(first, "w1#1") is Renewal.LOST      # ownership checked: c1 cannot steal it back
    assert not queue.alive("a", "w1#1")
    assert queue.renew(second, "w2#2") is Renewal.KEPT


def test_a_fenced_attempt_never_acks_its_successors_delivery(queue):
    queue.enqueue("a")
    stale = queue.lease("c1", 0.1)
    queue.renew(stale, "w1#1")
    time.sleep(LEASE * 1.3)
    fresh = queue.lease("c2", 0.1)
    queue.renew(fresh, "w2#2")
    assert not queue.ack(stale, "w1#1") and not queue.requeue(stale, "w1#1")
    assert queue.depth() == {"waiting": 0, "leased": 1} and queue.queued_ids() == {"a"}
    assert queue.renew(fresh, "w2#2") is Renewal.KEPT and queue.alive("a", "w2#2")
    assert queue.ack(fresh, "w2#2")
    assert queue.depth() == {"waiting": 0, "leased": 0} and queue.queued_ids() == set()
    assert not queue.alive("a", "w2#2")


def test_requeue_hands_the_job_back_with_one_marker(queue):
    queue.enqueue("a")
    lease = queue.lease("c1", 0.1)
    queue.renew(lease, "w1#1")
    assert queue.requeue(lease, "w1#1")
    assert queue.depth() == {"waiting": 1, "leased": 0} and not queue.enqueue("a")
    again = queue.lease("c2", 0.1)
    assert again is not None and again.job_id == "a" and again.entry_id != lease.entry_id


def test_enqueue_unless_alive_and_the_orphan_grace(queue):
    queue.enqueue("a")
    lease = queue.lease("c1", 0.1)
    queue.renew(lease, "w1#1")
    queue.ack(lease)                                        # the marker is gone, the heartbeat beats on
    assert not queue.enqueue("a", unless_alive="w1#1")
    assert queue.orphans({"x", "y"}, 0.5) == set()          # first seen now
    time.sleep(0.6)
    assert queue.orphans({"x"}, 0.5) == {"x"}               # y is forgotten
    assert queue.orphans({"y"}, 0.5) == set()               # ... and starts over


def test_a_running_attempt_adopts_its_job_when_redis_lost_its_data(redis_server):
    from services.queue.redis_queue import RedisJobQueue, connect

    client = connect(redis_server.url)
    client.flushall()
    queue = RedisJobQueue(client, LEASE)
    queue.enqueue("a")
    lease = queue.lease("c1", 0.1)
    assert queue.renew(lease, "w1#1") is Renewal.KEPT
    client.flushall()                                       # a restart without persistence
    assert queue.renew(lease, "w1#1") is Renewal.ADOPTED
    assert queue.queued_ids() == {"a"} and queue.alive("a", "w1#1") and not queue.enqueue("a")
    assert queue.renew(lease, "w1#1") is Renewal.KEPT
    assert queue.renew(lease, "other#2") is Renewal.LOST    # another attempt of the job cannot adopt it too
    assert queue.ack(lease, "w1#1") and queue.queued_ids() == set()
    queue.enqueue("a")
    adopter = queue.lease("c1", 0.1)
    client.flushall()
    assert queue.renew(adopter, "w1#2") is Renewal.ADOPTED
    time.sleep(LEASE * 1.3)                                 # the adopting worker died too
    assert queue.queued_ids() == set()                      # its marker no longer holds the job
    assert queue.enqueue("a") and queue.lease("c2", 0.1).job_id == "a"
    client.flushall()
    queue.enqueue("b")
    lease_b = queue.lease("c1", 0.1)
    client.flushall()
    queue.enqueue("b")                                      # queued anew before the runner renewed: it lost
    assert queue.renew(lease_b, "w1#1") is Renewal.LOST


@pytest.mark.parametrize("mode", ["redis", "local"])
def test_event_bus_wait_async_wakes_on_publish_without_threads(mode, redis_server):
    if mode == "redis":
        from services.queue.redis_queue import RedisEventBus, connect

        bus = RedisEventBus(connect(redis_server.url), redis_server.url)
    else:
        bus = LocalEventBus()

    async def scenario():
        import threading

        threads = threading.active_count()
        waiters = [asyncio.create_task(bus.wait_async("j", 0, 5.0)) for _ in range(50)]
        await asyncio.sleep(0.2)
        assert threading.active_count() == threads            # 50 waits, no thread each
        started = time.monotonic()
        await asyncio.to_thread(bus.publish, "j", {"seq": 1, "type": "x"})   # from another thread
        assert all(await asyncio.gather(*waiters)) and time.monotonic() - started < 1.0
        assert await bus.wait_async("j", 0, 0.1)                # already newer: at once
        assert not await bus.wait_async("j", 1, 0.2)            # nothing newer: times out
        await bus.aclose()

    asyncio.run(scenario())


def test_stream_slots_are_shared_by_api_processes(redis_server):
    from services.queue.redis_queue import RedisEventBus, RedisStreamSlots, connect

    first, second = (RedisStreamSlots(RedisEventBus(connect(redis_server.url), redis_server.url), ttl_seconds=1.0)
                     for _ in range(2))

    async def scenario():
        held = [await first.acquire("k", 3), await second.acquire("k", 3), await first.acquire("k", 3)]
        assert all(held) and await second.acquire("k", 3) is None
        assert await second.acquire("other", 3) is not None
        await first.release("k", held[0])
        again = await second.acquire("k", 3)
        assert again is not None
        await second.refresh("k", again)
        await asyncio.sleep(1.2)                                # the holders died without releasing
        assert await first.acquire("k", 3) is not None
        for slots in (first, second):
            await slots.bus.aclose()

    asyncio.run(scenario())


def test_local_stream_slots_cap():
    slots = LocalStreamSlots()

    async def scenario():
        a = await slots.acquire("k", 1)
        assert a and await slots.acquire("k", 1) is None
        await slots.release("k", a)
        assert await slots.acquire("k", 1)

    asyncio.run(scenario())


def test_stream_slots_fail_closed_when_redis_errors():
    """A slots object whose Redis is unreachable refuses (SlotsUnavailable: the route's 503), it
    never lets a stream in uncounted."""
    from harness.cluster import free_port
    from services.queue.base import SlotsUnavailable
    from services.queue.redis_queue import RedisEventBus, RedisStreamSlots, connect

    url = f"redis://127.0.0.1:{free_port()}/0"                # nothing listens there
    slots = RedisStreamSlots(RedisEventBus(connect(url), url))

    async def scenario():
        with pytest.raises(SlotsUnavailable):
            await slots.acquire("k", 3)
        await slots.bus.aclose()

    asyncio.run(scenario())


def test_stream_slots_fail_closed_when_the_command_pool_is_busy(redis_server):
    """Every command connection held (here by two long BLPOPs): acquiring a slot fails within about
    a second instead of counting nothing (the probe's 100 extra streams of issue 27)."""
    from services.queue.base import SlotsUnavailable
    from services.queue.redis_queue import RedisEventBus, RedisStreamSlots, connect

    bus = RedisEventBus(connect(redis_server.url), redis_server.url, connections=2)
    slots = RedisStreamSlots(bus)

    async def scenario():
        client = bus.async_client()
        held = [asyncio.create_task(client.blpop([f"nothing-{i}"], timeout=4)) for i in range(2)]
        await asyncio.sleep(0.3)
        started = time.monotonic()
        with pytest.raises(SlotsUnavailable):
            await slots.acquire("k", 3)
        assert time.monotonic() - started < 3.0
        await asyncio.gather(*held)
        assert await slots.acquire("k", 3) is not None         # free again: counted as usual
        await bus.aclose()

    asyncio.run(scenario())


def test_stream_waits_share_one_connection_and_leave_the_commands_free(redis_server):
    """300 waits on 300 streams: one XREAD BLOCK over all of them (the wait pool has two
    connections), the command pool stays free for the slots of everyone else, and an event wakes
    the waiters of its stream only."""
    from services.queue.redis_queue import RedisEventBus, RedisStreamSlots, connect

    client = connect(redis_server.url)
    bus = RedisEventBus(client, redis_server.url, connections=4)
    slots = RedisStreamSlots(bus)

    async def scenario():
        before = len(client.client_list())
        waiters = {i: asyncio.create_task(bus.wait_async(f"s{i}", 0, 8.0)) for i in range(300)}
        await asyncio.sleep(0.5)
        assert len(client.client_list()) - before <= 4 + 2      # command pool + the wait's two
        started = time.monotonic()
        assert await slots.acquire("other-tenant", 3) is not None
        assert time.monotonic() - started < 0.5
        await asyncio.to_thread(bus.publish, "s7", {"seq": 1, "type": "x"})
        assert await asyncio.wait_for(waiters.pop(7), 2.0)
        await asyncio.sleep(0.2)
        assert not any(task.done() for task in waiters.values())
        await asyncio.to_thread(bus.publish, "s8", {"seq": 1, "type": "x"})  # a stream that joined earlier
        assert await asyncio.wait_for(waiters.pop(8), 2.0)
        late = asyncio.create_task(bus.wait_async("late", 0, 8.0))  # joins while the read blocks
        await asyncio.sleep(0.2)
        started = time.monotonic()
        await asyncio.to_thread(bus.publish, "late", {"seq": 1, "type": "x"})
        assert await asyncio.wait_for(late, 2.0) and time.monotonic() - started < 1.0
        for task in waiters.values():
            task.cancel()
        await asyncio.gather(*waiters.values(), return_exceptions=True)
        await bus.aclose()

    asyncio.run(scenario())

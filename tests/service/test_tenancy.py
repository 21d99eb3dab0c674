"""Tenants share the service (issue 38), against a real Redis server and the in-process queue:
the per-key active-jobs cap is checked and taken in one step under concurrency, and workers take
waiting jobs owner by owner (least recently served first), not first in first out."""

from __future__ import annotations

import threading

import pytest

from harness.cluster import Redis, small_job
from schemas.job import JobSpec
from schemas.records import ACTIVE
from services.jobs.service import Caller, JobService, TooManyJobs
from services.queue.local import LocalEventBus, LocalJobQueue
from services.store.local import FolderStore

ALICE, BOB = Caller("alice"), Caller("bob")


@pytest.fixture(scope="module")
def redis_server():
    server = Redis().start()
    yield server
    server.kill()


def make_queue(kind: str, redis_server, lease: float = 30.0):
    if kind == "local":
        return LocalJobQueue(lease)
    from services.queue.redis_queue import RedisJobQueue, connect

    client = connect(redis_server.url)
    client.flushall()
    return RedisJobQueue(client, lease)


@pytest.mark.parametrize("kind", ["redis", "local"])
def test_48_concurrent_submissions_against_a_cap_of_32_make_exactly_32_active_jobs(kind, redis_server, tmp_path):
    """The outside probe got 33 active jobs of 32: the cap was counted and taken in two steps."""
    service = JobService(FolderStore(tmp_path), make_queue(kind, redis_server), LocalEventBus())
    spec = JobSpec.model_validate(small_job("direct"))
    created, refused = [], []
    start = threading.Barrier(48)

    def submit() -> None:
        start.wait()
        try:
            created.append(service.submit(spec, ALICE, max_active=32)[0].id)
        except TooManyJobs:
            refused.append(1)

    threads = [threading.Thread(target=submit) for _ in range(48)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(120)
    active = sum(1 for r in service.records() if r.owner == "alice" and r.status in ACTIVE)
    assert (len(created), len(refused), active) == (32, 16, 32)
    assert service.queue.depth()["waiting"] == 32
    bob, _ = service.submit(spec, BOB, max_active=32)           # another key's cap is its own
    assert bob.owner == "bob"


@pytest.mark.parametrize("kind", ["redis", "local"])
def test_a_keys_job_waits_for_one_job_of_another_key_not_its_queue(kind, redis_server):
    queue = make_queue(kind, redis_server)
    for i in range(4):
        assert queue.enqueue(f"alice-{i}", owner="alice")
    first = queue.lease("w1", 0.1)
    assert first is not None and first.job_id == "alice-0"
    assert queue.enqueue("bob-0", owner="bob")
    assert queue.depth()["waiting"] == 4
    order = [queue.lease("w1", 0.1).job_id for _ in range(4)]
    assert order == ["bob-0", "alice-1", "alice-2", "alice-3"]
    assert queue.lease("w1", 0.05) is None and queue.depth()["waiting"] == 0


@pytest.mark.parametrize("kind", ["redis", "local"])
def test_keys_take_turns_and_a_job_handed_back_goes_first(kind, redis_server):
    queue = make_queue(kind, redis_server)
    for owner in ("alice", "bob", "carol"):
        for i in range(3):
            queue.enqueue(f"{owner}-{i}", owner=owner)
    leases = [queue.lease("w1", 0.1) for _ in range(3)]
    assert [lease.job_id for lease in leases] == ["alice-0", "bob-0", "carol-0"]
    assert queue.requeue(leases[1], "w1#1")                      # interrupted: it goes ahead of the others
    order = [queue.lease("w2", 0.1).job_id for _ in range(7)]
    assert order == ["bob-0", "alice-1", "bob-1", "carol-1", "alice-2", "bob-2", "carol-2"]


@pytest.mark.parametrize("kind", ["redis", "local"])
def test_a_worker_waiting_for_work_wakes_on_enqueue(kind, redis_server):
    queue = make_queue(kind, redis_server)
    got: list = []
    waiter = threading.Thread(target=lambda: got.append(queue.lease("w1", 5.0)))
    waiter.start()
    threading.Event().wait(0.3)
    queue.enqueue("late", owner="bob")
    waiter.join(3.0)
    assert not waiter.is_alive() and got and got[0].job_id == "late"

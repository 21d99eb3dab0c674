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
def test_jobs_canceled_while_queued_spend_none_of_their_keys_turns(kind, redis_server):
    """Bob's jobs canceled while queued stood ahead of his new one and each took a turn of his:
    alice's whole queue ran before it (seen in tests/e2e/test_adversarial_tenants.py)."""
    queue = make_queue(kind, redis_server)
    for i in range(3):
        queue.enqueue(f"alice-{i}", owner="alice")
        queue.enqueue(f"bob-old-{i}", owner="bob")
    for i in range(3):
        assert queue.withdraw(f"bob-old-{i}", owner="bob")
    assert not queue.withdraw("bob-old-0", owner="bob")          # only once
    assert queue.lease("w1", 0.1).job_id == "alice-0"
    queue.enqueue("bob-new", owner="bob")
    order = [queue.lease("w1", 0.1).job_id for _ in range(3)]
    assert order == ["bob-new", "alice-1", "alice-2"]
    assert queue.lease("w1", 0.05) is None and queue.depth()["waiting"] == 0
    assert queue.enqueue("bob-old-0", owner="bob")               # a withdrawn job holds no marker


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


@pytest.mark.parametrize("kind", ["redis", "local"])
def test_a_key_runs_at_most_its_cap_of_jobs_and_a_free_worker_takes_another_keys(kind, redis_server):
    queue = make_queue(kind, redis_server)
    queue.running_per_owner = 2
    for i in range(4):
        queue.enqueue(f"alice-{i}", owner="alice")
    first, second = queue.lease("w1", 0.1), queue.lease("w2", 0.1)
    assert (first.job_id, second.job_id, queue.running("alice")) == ("alice-0", "alice-1", 2)
    assert queue.lease("w3", 0.05) is None                       # alice is at her cap
    queue.enqueue("bob-0", owner="bob")
    assert queue.lease("w3", 0.1).job_id == "bob-0"
    assert queue.ack(first, "w1#1") and queue.running("alice") == 1
    assert queue.lease("w1", 0.1).job_id == "alice-2"


def test_a_key_at_its_storage_quota_is_refused_and_a_job_gets_what_the_key_has_left(tmp_path, monkeypatch):
    import services.jobs.service as module
    from services.jobs.quotas import StorageQuota, attempt_budget

    monkeypatch.setattr(module, "ROOM_SECONDS", 0.0)          # sum the key's bytes at every submission
    from services.settings import Limits

    service = JobService(FolderStore(tmp_path), LocalJobQueue(), LocalEventBus())
    spec = JobSpec.model_validate(small_job("direct"))
    limits = Limits(key_bytes=3 << 20, job_bytes=2 << 20)
    first, _ = service.submit(spec, ALICE, limits=limits)
    assert attempt_budget(service.states, first.id, limits).limit == "NDRF_MAX_JOB_BYTES"
    service.store.put(f"{first.id}/blob", b"x" * (2 << 20))         # what a job wrote
    second, _ = service.submit(spec, ALICE, limits=limits)
    budget = attempt_budget(service.states, second.id, limits)
    assert budget.bytes < 1 << 20 and budget.limit.startswith("NDRF_MAX_KEY_BYTES")
    service.store.put(f"{second.id}/blob", b"x" * (1 << 20))
    with pytest.raises(StorageQuota, match="NDRF_MAX_KEY_BYTES"):
        service.submit(spec, ALICE, limits=limits)
    assert service.store.get(f"{first.id}/blob") == b"x" * (2 << 20)  # nothing written is touched
    service.submit(spec, BOB, limits=limits)                         # another key's quota is its own


def test_a_key_has_at_most_experiments_per_key_unfinished_experiments(tmp_path):
    from schemas.experiments import ExperimentSpec
    from services.experiments.service import ExperimentService, TooManyExperiments
    from services.settings import Limits

    service = JobService(FolderStore(tmp_path), LocalJobQueue(), LocalEventBus())
    experiments = ExperimentService(service, Limits(experiments_per_key=2))
    spec = ExperimentSpec.model_validate({"base": small_job("direct"), "grid": {"learning_rate": [0.1, 0.2]}})
    for _ in range(2):
        experiments.create(spec, ALICE)
    with pytest.raises(TooManyExperiments, match="NDRF_MAX_EXPERIMENTS_PER_KEY"):
        experiments.create(spec, ALICE)
    experiments.create(spec, BOB)

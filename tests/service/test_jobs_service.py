"""The job service as pure logic over a folder store and the in-process queue (no processes)."""

from __future__ import annotations

import time

import pytest

from harness.cluster import small_job
from schemas.job import JobSpec
from schemas.records import JobStatus
from services.jobs.service import Caller, JobService, TooManyJobs
from services.jobs.state import Conflict, UnknownJob
from services.queue.local import LocalEventBus, LocalJobQueue
from services.store.local import FolderStore

ALICE, BOB, ADMIN = Caller("alice"), Caller("bob"), Caller("root", admin=True)


@pytest.fixture
def service(tmp_path):
    return JobService(FolderStore(tmp_path), LocalJobQueue(), LocalEventBus())


def spec(**extra):
    return JobSpec.model_validate(small_job("direct", **extra))


def test_jobs_belong_to_their_key(service):
    record, created = service.submit(spec(), ALICE)
    assert created and record.owner == "alice" and service.queue.queued_ids() == {record.id}
    assert [r.id for r in service.records(ALICE)] == [record.id]
    assert list(service.records(BOB)) == [] and [r.id for r in service.records(ADMIN)] == [record.id]
    for call in (service.record, service.files, service.cancel, service.delete):
        with pytest.raises(UnknownJob):
            call(record.id, BOB)
    with pytest.raises(UnknownJob):
        service.record("../../etc/passwd", ADMIN)                  # ids are checked before any lookup


def test_idempotency_keys_are_per_key_and_claimed_atomically(service):
    first, created = service.submit(spec(), ALICE, idempotency_key="k")
    again, created_again = service.submit(spec(), ALICE, idempotency_key="k")
    other, created_other = service.submit(spec(), BOB, idempotency_key="k")
    assert created and not created_again and again.id == first.id
    assert created_other and other.id != first.id
    assert service.find_idempotent(ALICE, "k").id == first.id


def test_a_claim_whose_job_never_appeared_is_taken_over_once_stale(service, monkeypatch):
    import services.jobs.service as module

    claim = service._claim_key(ALICE, "lost")
    service.store.put(claim, b"00000000000100000000")              # a writer died after claiming (1970)
    record, created = service.submit(spec(), ALICE, idempotency_key="lost")
    assert created and service.store.get(claim).decode() == record.id
    fresh = service._claim_key(ALICE, "fresh")
    service.store.put(fresh, module.new_job_id().encode())          # being processed right now
    with pytest.raises(Conflict, match="still being processed"):
        service.submit(spec(), ALICE, idempotency_key="fresh")


def test_a_key_has_a_cap_on_active_jobs(service):
    for _ in range(2):
        service.submit(spec(), ALICE, max_active=2)
    with pytest.raises(TooManyJobs, match="NDRF_MAX_ACTIVE_JOBS_PER_KEY"):
        service.submit(spec(), ALICE, max_active=2)
    service.submit(spec(), BOB, max_active=2)                       # another key's budget


def test_cancel_delete_and_retention(service):
    queued, _ = service.submit(spec(), ALICE)
    assert service.cancel(queued.id, ALICE).status is JobStatus.CANCELED
    with pytest.raises(Conflict):
        service.cancel(queued.id, ALICE)                            # already finished
    running, _ = service.submit(spec(), ALICE)
    service.states.transition(running.id, JobStatus.RUNNING, attempt="w#1")
    after = service.cancel(running.id, ALICE)
    assert after.status is JobStatus.RUNNING and after.cancel_requested   # its runner stops it
    with pytest.raises(Conflict, match="cancel it first"):
        service.delete(running.id, ALICE)
    service.delete(queued.id, ALICE)
    assert queued.id not in service.ids()
    old, _ = service.submit(spec(), ALICE)
    service.states.transition(old.id, JobStatus.SUCCEEDED)
    assert service.sweep(retention_days=1.0) == []                  # changed just now: kept
    time.sleep(0.01)                                                # record times have millisecond resolution
    assert service.sweep(retention_days=1e-9) == [old.id]           # finished more than ~0.1 ms ago
    assert running.id in service.ids()                              # active jobs are never swept


def test_an_idempotency_claim_goes_with_its_job(service):
    """Deleting a job (or retention sweeping it) deletes its idempotency claim: no claim files pile up,
    and the key then makes a new job."""
    first, created = service.submit(spec(), ALICE, "retry-me")
    assert created and service.find_idempotent(ALICE, "retry-me").id == first.id
    service.cancel(first.id, ALICE)
    service.delete(first.id, ALICE)
    assert service.find_idempotent(ALICE, "retry-me") is None
    second, created = service.submit(spec(), ALICE, "retry-me")
    assert created and second.id != first.id
    service.cancel(second.id, ALICE)
    time.sleep(0.01)
    assert service.sweep(retention_days=1e-9) == [second.id]
    assert service.store.get(service._claim_key(ALICE, "retry-me")) is None

"""The one owner of a job's state: compare-and-set transitions, the fence, status events."""

from __future__ import annotations

import threading

import pytest

from schemas.records import JobRecord, JobStatus
from services.jobs.state import Conflict, Fenced, JobStates, UnknownJob, now_iso
from services.queue.local import LocalEventBus
from services.store.local import FolderStore


@pytest.fixture(params=["folder", "s3"])
def states(request, tmp_path):
    store = FolderStore(tmp_path) if request.param == "folder" else request.getfixturevalue("s3_store")
    return JobStates(store, LocalEventBus())


def new(states, job_id="00000000000000000001"):
    now = now_iso()
    return states.create(JobRecord(id=job_id, status=JobStatus.QUEUED, method="direct", scene="cornell-box",
                                   created=now, updated=now, iterations=3))


def events(states, job_id="00000000000000000001"):
    return states.store.read_events(f"{job_id}/")[0]


def test_create_refuses_an_existing_id_and_logs_the_first_status(states):
    new(states)
    with pytest.raises(Conflict):
        new(states)
    assert [(e["type"], e["status"]) for e in events(states)] == [("status", "queued")]


def test_transitions_set_times_and_log_status_changes_only(states):
    new(states)
    running = states.transition("00000000000000000001", JobStatus.RUNNING, attempt="w#1")
    assert running.started and running.attempt == "w#1" and not running.finished
    states.transition("00000000000000000001", fence="w#1", iteration=0)        # progress: no status event
    done = states.transition("00000000000000000001", JobStatus.SUCCEEDED, fence="w#1", expect={JobStatus.RUNNING})
    assert done.finished and done.iteration == 0
    assert [e["status"] for e in events(states)] == ["queued", "running", "succeeded"]


def test_the_fence_stops_a_stale_attempt(states):
    new(states)
    states.transition("00000000000000000001", JobStatus.RUNNING, attempt="w#1")
    states.transition("00000000000000000001", JobStatus.RUNNING, attempt="v#2")   # taken over
    with pytest.raises(Fenced, match="v#2"):
        states.transition("00000000000000000001", fence="w#1", iteration=5)
    assert states.get("00000000000000000001").iteration is None


def test_expected_status_and_expected_attempt(states):
    new(states)
    with pytest.raises(Conflict, match="queued"):
        states.transition("00000000000000000001", JobStatus.SUCCEEDED, expect={JobStatus.RUNNING})
    states.transition("00000000000000000001", JobStatus.RUNNING, expect_attempt=None, attempt="w#1")
    with pytest.raises(Conflict, match="claimed"):     # a second claimer read the record before the first won
        states.transition("00000000000000000001", JobStatus.RUNNING, expect_attempt=None, attempt="v#1")
    assert states.get("00000000000000000001").attempt == "w#1"


def test_unknown_jobs(states):
    with pytest.raises(UnknownJob):
        states.get("00000000000000000009")
    with pytest.raises(UnknownJob):
        states.transition("00000000000000000009", JobStatus.CANCELED)


def _race(*calls) -> list:
    """Run the calls at once (a barrier); each result is the call's return value or its exception."""
    results: list = [None] * len(calls)
    barrier = threading.Barrier(len(calls))

    def run(i):
        barrier.wait()
        try:
            results[i] = calls[i]()
        except Exception as exc:
            results[i] = exc

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(calls))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return results


def _machines(states):
    """Two JobStates over two store clients of the same bucket (or folder): two machines."""
    store = states.store
    if isinstance(store, FolderStore):
        return states, JobStates(FolderStore(store.root))
    from harness.s3server import ACCESS_KEY, REGION, SECRET_KEY
    from services.store.s3 import S3Store

    return states, JobStates(S3Store(store.url, endpoint=store.endpoint, access_key_id=ACCESS_KEY,
                                     secret_access_key=SECRET_KEY, region=REGION))


def test_a_stale_attempt_finishing_and_a_takeover_racing_have_exactly_one_winner(states):
    """The fenced update: the old attempt reports success while another worker claims the job
    (its lease expired). Either the finish lands (the claim then sees a finished job) or the claim
    lands (the finish is fenced off), never both, over 20 rounds on two clients."""
    here, there = _machines(states)
    outcomes = set()
    for n in range(20):
        job_id = f"{n + 1:020d}"
        new(here, job_id)
        here.transition(job_id, JobStatus.RUNNING, attempt="old#1")
        finish = lambda j=job_id: here.transition(j, JobStatus.SUCCEEDED, fence="old#1", expect={JobStatus.RUNNING})
        claim = lambda j=job_id: there.transition(j, JobStatus.RUNNING, expect={JobStatus.QUEUED, JobStatus.RUNNING},
                                                  expect_attempt="old#1", attempt="new#2")
        finished, claimed = _race(finish, claim)
        record = here.get(job_id)
        if isinstance(finished, JobRecord):
            assert isinstance(claimed, Conflict) and record.status is JobStatus.SUCCEEDED and record.attempt == "old#1"
            outcomes.add("finish won")
        else:
            assert isinstance(finished, Fenced) and isinstance(claimed, JobRecord)
            assert record.status is JobStatus.RUNNING and record.attempt == "new#2"
            outcomes.add("claim won")
        statuses = [e["status"] for e in events(here, job_id)]   # a claim of a running job logs no status
        assert statuses == ["queued", "running"] + (["succeeded"] if record.status is JobStatus.SUCCEEDED else [])
    assert outcomes   # (which side wins each round is up to the scheduler)


def test_two_workers_claiming_one_job_at_once_have_exactly_one_winner(states):
    here, there = _machines(states)
    for n in range(20):
        job_id = f"{n + 1:020d}"
        new(here, job_id)
        claims = [lambda s=s, w=w, j=job_id: s.transition(j, JobStatus.RUNNING, expect={JobStatus.QUEUED},
                                                          expect_attempt=None, attempt=f"{w}#1")
                  for s, w in ((here, "a"), (there, "b"), (here, "c"), (there, "d"))]
        results = _race(*claims)
        winners = [r for r in results if isinstance(r, JobRecord)]
        assert len(winners) == 1 and all(isinstance(r, Conflict) for r in results if r not in winners)
        assert here.get(job_id).attempt == winners[0].attempt

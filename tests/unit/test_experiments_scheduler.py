"""The experiment scheduler over a real store, queue and job service, with stand-in workers that
move job records as the real ones do (no scene, no child process): max_concurrent under two
concurrent schedulers, interactive jobs first, cancel, retry of failed runs only, appends, and a
scheduler that died half-way through an admission."""

from __future__ import annotations

import time

import pytest

from harness.cluster import small_job, wait_until
from schemas.experiments import ExperimentAppend, ExperimentSpec
from schemas.job import JobSpec
from schemas.records import FINISHED, JobStatus
from services.experiments.scheduler import Scheduler
from services.experiments.service import ExperimentService
from services.experiments.state import ExperimentConflict
from services.jobs.service import Caller, JobService
from services.queue.local import LocalEventBus, LocalJobQueue
from services.settings import Limits
from services.store.local import FolderStore
from tests.support.experiments import FakeWorker


@pytest.fixture
def setup(tmp_path):
    store, queue, events = FolderStore(tmp_path), LocalJobQueue(), LocalEventBus()
    jobs = JobService(store, queue, events)
    experiments = ExperimentService(jobs, Limits())
    workers, schedulers = [], []

    class Setup:
        def __init__(self):
            self.jobs, self.experiments, self.queue, self.store = jobs, experiments, queue, store

        def workers(self, n, hold=0.15, fails=lambda spec: False):
            workers.extend(FakeWorker(jobs, hold, fails) for _ in range(n))

        def scheduler(self, interval=0.02):
            scheduler = Scheduler(experiments, queue, interval=interval)
            scheduler.start()
            schedulers.append(scheduler)
            return scheduler

        def create(self, **sweep):
            spec = ExperimentSpec.model_validate({"base": small_job("direct", iterations=2), **sweep})
            return experiments.create(spec)

        def wait_done(self, exp_id, timeout=30):
            return wait_until(lambda: (r := experiments.states.get(exp_id)).status.finished and r, timeout, 0.02,
                              what="the experiment to finish")

    yield Setup()
    for s in schedulers:
        s.stop()
    for w in workers:
        w.stop.set()
        w.thread.join(5)


def running_jobs(setup, exp_id):
    return [r for r in setup.jobs.records() if r.experiment == exp_id and r.status is JobStatus.RUNNING]


def test_max_concurrent_holds_with_two_schedulers_and_four_workers(setup):
    setup.workers(4, hold=0.1)
    record = setup.create(grid={"learning_rate": [0.01, 0.02, 0.03, 0.04]}, seeds=[1, 2], max_concurrent=2)
    assert record.status.value == "queued" and len(record.runs) == 8
    assert list(setup.jobs.records()) == []                        # nothing is queued before the scheduler
    setup.scheduler()
    setup.scheduler()                                              # two processes' schedulers, no lock
    peak, active_peak = 0, 0
    deadline = time.monotonic() + 30
    while not setup.experiments.states.get(record.id).status.finished and time.monotonic() < deadline:
        peak = max(peak, len(running_jobs(setup, record.id)))
        active = [r for r in setup.jobs.records() if r.experiment == record.id and r.status not in FINISHED]
        active_peak = max(active_peak, len(active))
        time.sleep(0.005)
    done = setup.wait_done(record.id)
    assert done.status.value == "succeeded" and all(r.status == "succeeded" for r in done.runs)
    assert peak == 2 and active_peak <= 2
    jobs = [r for r in setup.jobs.records() if r.experiment == record.id]
    assert len(jobs) == 8 and {tuple(sorted(j.varied.items())) for j in jobs} == \
        {tuple(sorted(r.values.items())) for r in done.runs}
    events = wait_until(lambda: (e := setup.experiments.states.read_events(record.id)[0])[-1]["type"] == "status"
                        and e, 5, 0.01, what="the final status event")
    assert events[-1]["status"] == "succeeded"
    assert {(e["index"], e["status"]) for e in events if e["type"] == "run"} >= {(i, s) for i in range(8)
                                                                              for s in ("queued", "succeeded")}


def test_interactive_jobs_go_first_runs_enter_the_queue_one_at_a_time(setup):
    record = setup.create(seeds=list(range(10)), max_concurrent=10)
    scheduler = Scheduler(setup.experiments, setup.queue)
    assert scheduler.tick() == 1                         # nobody leases it: one run waits in the queue, no more
    assert scheduler.tick() == 0 and setup.queue.depth()["waiting"] == 1
    interactive, _ = setup.jobs.submit(JobSpec.model_validate(small_job("prb")))
    leased = [setup.queue.lease("w", 0.1).job_id for _ in range(2)]
    assert leased[1] == interactive.id                     # behind one run, not behind ten
    assert scheduler.tick() == 1
    assert sum(r.status == "pending" for r in setup.experiments.states.get(record.id).runs) == 8


def test_cancel_stops_the_rest_and_retry_reruns_failed_runs_only(setup):
    broken = {"on": True}                                # the runs with learning rate 0.02 fail, until fixed
    setup.workers(2, hold=0.3, fails=lambda spec: broken["on"] and spec.learning_rate == 0.02)
    setup.scheduler()
    record = setup.create(grid={"learning_rate": [0.01, 0.02]}, seeds=[1, 2], max_concurrent=2)
    done = setup.wait_done(record.id)
    assert done.status.value == "failed"
    statuses = {r.index: r.status for r in done.runs}
    assert statuses == {0: "succeeded", 1: "succeeded", 2: "failed", 3: "failed"}
    first_jobs = {r.index: r.job for r in done.runs}

    broken["on"] = False
    again, rerun = setup.experiments.retry(record.id)
    assert rerun == [2, 3] and again.status.value == "running"
    done = setup.wait_done(record.id)
    assert done.status.value == "succeeded"
    assert {r.index: r.job for r in done.runs if r.index < 2} == {0: first_jobs[0], 1: first_jobs[1]}
    assert all(done.runs[i].job != first_jobs[i] and done.runs[i].jobs == [first_jobs[i], done.runs[i].job]
               for i in (2, 3))
    assert len([r for r in setup.jobs.records() if r.experiment == record.id]) == 6
    with pytest.raises(ExperimentConflict, match="no failed or canceled runs"):
        setup.experiments.retry(record.id)

    long = setup.create(seeds=list(range(6)), max_concurrent=2)
    wait_until(lambda: len(running_jobs(setup, long.id)) == 2, 10, 0.01, what="two running runs")
    canceled = setup.experiments.cancel(long.id)
    assert sum(r.status == "canceled" for r in canceled.runs) == 4          # the pending ones, at once
    done = setup.wait_done(long.id)
    assert done.status.value == "canceled" and all(r.status == "canceled" for r in done.runs)
    assert len([r for r in setup.jobs.records() if r.experiment == long.id]) == 2      # nothing more admitted
    with pytest.raises(ExperimentConflict, match="already canceled"):
        setup.experiments.cancel(long.id)


def test_append_adds_only_new_runs_and_reruns_nothing(setup):
    setup.workers(2, hold=0.05)
    setup.scheduler()
    record = setup.create(seeds=[1, 2], max_concurrent=2)
    done = setup.wait_done(record.id)
    jobs_before = {r.index: r.job for r in done.runs}
    appended, added = setup.experiments.append(record.id, ExperimentAppend(seeds=[3, 4, 2]))
    assert added == [2, 3] and len(appended.runs) == 4
    done = setup.wait_done(record.id)
    assert done.status.value == "succeeded" and {r.index: r.job for r in done.runs[:2]} == jobs_before
    assert len([r for r in setup.jobs.records() if r.experiment == record.id]) == 4
    assert setup.experiments.append(record.id, ExperimentAppend(seeds=[4]))[1] == []


def test_an_admission_half_done_by_a_dead_scheduler_is_completed_once(setup):
    record = setup.create(seeds=[1, 2], max_concurrent=1)
    dead = Scheduler(setup.experiments, setup.queue)

    def reserve_only(current):        # what admit() does before submitting, then the process dies
        run = current.runs[0]
        run.status, run.admissions, run.since = "admitting", 1, time.time() - 60
        return current

    setup.experiments.states.update(record.id, reserve_only)
    assert dead.tick() == 0                              # the stale admission holds the only slot...
    runs = setup.experiments.states.get(record.id).runs
    assert runs[0].status == "queued" and runs[0].job and runs[1].status == "pending"   # ...and is completed
    assert len(list(setup.jobs.records())) == 1
    again = dead._complete(setup.experiments.states.get(record.id), runs[0].model_copy(update={"admissions": 1}))
    assert again is not None and len(list(setup.jobs.records())) == 1    # idempotent: the same job, not two


def test_a_tick_reads_again_only_the_experiments_that_changed(setup, monkeypatch):
    # issue 38: 60 experiments of 200 runs, each read again every 0.5 s, took 20% of a core
    setup.jobs.submit(JobSpec.model_validate(small_job("direct")), Caller("bob"))
    ids = [setup.create(seeds=[1, 2, 3], max_concurrent=1).id for _ in range(5)]   # a job waits: none admitted
    scheduler = Scheduler(setup.experiments, setup.queue)
    read: list[str] = []
    get = setup.experiments.states.get
    monkeypatch.setattr(setup.experiments.states, "get", lambda exp_id: (read.append(exp_id), get(exp_id))[1])
    scheduler.tick()
    assert set(read) == set(ids)                                       # the first tick reads each
    read.clear()
    scheduler.tick()
    scheduler.tick()
    assert read == []                                                  # nothing changed: nothing read again
    setup.experiments.append(ids[2], ExperimentAppend(seeds=[4]))      # a change by another process
    read.clear()
    scheduler.tick()
    assert read == [ids[2]]

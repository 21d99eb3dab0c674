"""An experiment's warm start (``warm_start: "first_run"``) through the real scheduler, job
service and store, over the in-process queue and a real Redis queue, with stand-in workers
(tests/support/experiments.py): no dependent run gets a job before run 0 has succeeded, each then
carries ``warm_start: {job: run 0's job}``; a failed run 0 fails its dependents without a job, and
retry runs run 0 first again. And what creation refuses."""

from __future__ import annotations

import threading
import time

import pytest

from harness.cluster import Redis, small_job, wait_until
from schemas.experiments import ExperimentSpec
from schemas.job import JobSpec
from services.experiments.expand import InvalidExperiment
from services.experiments.scheduler import Scheduler
from services.experiments.service import ExperimentService
from services.jobs.service import JobService
from services.queue.local import LocalEventBus, LocalJobQueue
from services.settings import Limits
from services.store.job import JobFiles
from services.store.local import FolderStore
from tests.support.experiments import FakeWorker


@pytest.fixture(scope="module")
def redis_server():
    server = Redis().start()
    yield server
    server.kill()


@pytest.fixture(params=["local", "redis"])
def setup(request, tmp_path):
    if request.param == "local":
        queue = LocalJobQueue()
    else:
        from services.queue.redis_queue import RedisJobQueue, connect

        client = connect(request.getfixturevalue("redis_server").url)
        client.flushall()
        queue = RedisJobQueue(client, 5.0)
    jobs = JobService(FolderStore(tmp_path), queue, LocalEventBus())
    experiments = ExperimentService(jobs, Limits())
    failing = {"seed": None}
    workers = [FakeWorker(jobs, 0.6, fails=lambda spec: spec.seed == failing["seed"]) for _ in range(3)]
    schedulers = [Scheduler(experiments, queue, interval=0.02) for _ in range(2)]   # two processes' schedulers
    for scheduler in schedulers:
        scheduler.start()
    yield jobs, experiments, failing
    for scheduler in schedulers:
        scheduler.stop()
    for worker in workers:
        worker.stop.set()
        worker.thread.join(5)


def spec_of(jobs: JobService, job_id: str) -> JobSpec:
    return JobSpec.model_validate(JobFiles(jobs.store, job_id).read(JobFiles.SPEC))


class Watch(threading.Thread):
    """Samples the experiment's jobs: a dependent run's job must never exist before run 0's job
    succeeded."""

    def __init__(self, jobs: JobService, experiments: ExperimentService, exp_id: str):
        super().__init__(daemon=True)
        self.jobs, self.experiments, self.exp_id = jobs, experiments, exp_id
        self.violations, self.samples, self.peak_running = [], 0, 0
        self.stop = threading.Event()

    def run(self):
        while not self.stop.wait(0.005):
            record = self.experiments.states.get(self.exp_id)
            source = record.runs[0]
            source_status = self.jobs.states.get(source.job).status.value if source.job else None
            dependents = [r for r in record.runs[1:] if r.job]
            if dependents and source_status != "succeeded":
                self.violations.append((source_status, [r.index for r in dependents]))
            running = [r for r in self.jobs.records() if r.experiment == self.exp_id and r.status.value == "running"]
            self.peak_running = max(self.peak_running, len(running))
            self.samples += 1


def wait_done(experiments, exp_id, timeout=60):
    return wait_until(lambda: (r := experiments.states.get(exp_id)).status.finished and r, timeout, 0.02,
                      what="the experiment to finish")


def create(experiments, **sweep):
    return experiments.create(ExperimentSpec.model_validate({"base": small_job("ndrf-lhs", iterations=2), **sweep}))


def test_every_run_waits_for_run_0_then_starts_from_its_job(setup):
    jobs, experiments, _ = setup
    record = create(experiments, grid={"learning_rate": [0.01, 0.02]}, seeds=[1, 2, 3], max_concurrent=3,
                    warm_start="first_run")
    assert record.sweep["warm_start"] == {"source": "first_run", "parameters": False, "top_up_steps": None}
    watch = Watch(jobs, experiments, record.id)
    watch.start()
    done = wait_done(experiments, record.id)
    watch.stop.set()
    watch.join()
    assert done.status.value == "succeeded" and [r.status for r in done.runs] == ["succeeded"] * 6
    assert watch.samples > 20 and watch.violations == []
    assert watch.peak_running >= 2                     # the dependents then run side by side (max_concurrent 3)
    source = done.runs[0].job
    assert spec_of(jobs, source).warm_start is None
    for run in done.runs[1:]:
        warm = spec_of(jobs, run.job).warm_start
        assert warm is not None and warm.job == source and not warm.parameters and warm.top_up_steps is None


def test_a_failed_run_0_fails_the_others_without_jobs_and_retry_runs_it_first(setup):
    jobs, experiments, failing = setup
    failing["seed"] = 1
    record = create(experiments, seeds=[1, 2, 3], max_concurrent=2,
                    warm_start={"parameters": True, "top_up_steps": 3})
    done = wait_done(experiments, record.id)
    assert done.status.value == "failed" and [r.status for r in done.runs] == ["failed"] * 3
    assert [r.job is None for r in done.runs] == [False, True, True]
    assert all(r.error == "not run: run 0 (the warm-start source) failed" for r in done.runs[1:])
    rows = experiments.rows(done)
    assert rows[0].error == "boom" and rows[1].error == rows[2].error == done.runs[1].error
    assert len([r for r in jobs.records() if r.experiment == record.id]) == 1

    failed_source = done.runs[0].job
    failing["seed"] = None
    retried, again = experiments.retry(record.id)
    assert again == [0, 1, 2] and all(r.error is None for r in retried.runs)
    done = wait_done(experiments, record.id)
    assert done.status.value == "succeeded"
    source = done.runs[0].job
    assert source != failed_source and done.runs[0].jobs == [failed_source, source]
    for run in done.runs[1:]:
        warm = spec_of(jobs, run.job).warm_start
        assert warm is not None and warm.job == source and warm.parameters and warm.top_up_steps == 3
        assert jobs.states.get(run.job).created >= jobs.states.get(source).finished


def test_creation_refuses_runs_that_cannot_warm_start(tmp_path):
    experiments = ExperimentService(JobService(FolderStore(tmp_path), LocalJobQueue(), LocalEventBus()), Limits())

    def refused(base, **sweep):
        with pytest.raises(InvalidExperiment) as caught:
            experiments.create(ExperimentSpec.model_validate({"base": base, "warm_start": "first_run", **sweep}))
        return caught.value

    assert refused(small_job("prb")).field == "runs[0].method"
    assert refused(small_job(), grid={"method": ["ndrf-lhs", "direct"]}).field == "runs[1].method"
    error = refused(small_job(), grid={"training.radiance.direction_sh_degree": [4, 2]})
    assert error.field == "runs[1].warm_start" and "training.radiance" in error.message
    assert refused(small_job(warm_start={"job": "a" * 20})).field == "runs[0].warm_start"
    with pytest.raises(ValueError):
        ExperimentSpec.model_validate({"base": small_job(), "warm_start": "last_run"})
    cold = experiments.create(ExperimentSpec.model_validate({"base": small_job("prb"), "seeds": [1, 2]}))
    assert cold.sweep["warm_start"] is None


def test_runs_appended_later_warm_start_from_run_0_too(setup):
    jobs, experiments, _ = setup
    record = create(experiments, seeds=[1, 2], warm_start="first_run")
    done = wait_done(experiments, record.id)
    assert done.status.value == "succeeded"
    from schemas.experiments import ExperimentAppend

    _, added = experiments.append(record.id, ExperimentAppend(seeds=[3]))
    assert added == [2]
    time.sleep(0.1)
    done = wait_done(experiments, record.id)
    assert spec_of(jobs, done.runs[2].job).warm_start.job == done.runs[0].job

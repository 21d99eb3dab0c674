"""The experiment scheduler: admits pending runs into the job queue, above the queue.

A run becomes a job (``JobService.submit``: record, then enqueue) only when

1. its experiment has fewer than ``max_concurrent`` runs being admitted, queued or running, and
2. **nothing is waiting in the job queue** (``queue.depth()["waiting"] == 0``).

Rule 1 is exact across any number of workers and API processes: a run is reserved by a
compare-and-set of the experiment record that counts the active runs in the same step
(:mod:`services.experiments.state`), so two schedulers cannot both take the last slot. Rule 2 is
the fairness decision within a key: runs enter the queue one at a time and only when a worker is
about to be free, so a job the same key submits while a 100-run experiment is pending waits for the
next free worker (and at most one run admitted before it), never for the experiment. Between keys
the queue itself is fair (a share per key, :mod:`services.queue.base`).
Experiments with free slots are served oldest admission first, so two experiments interleave.

Admission is three steps, each safe to repeat: reserve the run (``admitting``, CAS), submit its
job with the idempotency key ``experiment:<id>:<run>:<admission>`` (a repeat returns the same
job), assign the job to the run (CAS). A scheduler that dies between steps leaves an
``admitting`` run that any scheduler completes after ``STALE_ADMISSION`` seconds.

Where it runs: every API process and every ``ndrf worker`` runs :meth:`Scheduler.run` on a thread
(the embedded mode's single process too). With Redis, a lease (``SET NX PX``) elects one ticking
process at a time, which only saves work: correctness rests on the compare-and-set. A tick also
refreshes each active experiment's run statuses from its jobs' records (a worker finishing a
job frees its slot at the next tick, every ``interval`` seconds).

A tick reads again only the experiments that may have changed (issue 38: 60 experiments of 200
runs took 20% of a core re-read every 0.5 s): those whose marker changed since the last read
(every change of a record writes a new marker, :meth:`ExperimentStates.active_marks`), and those
with a run admitting, queued or running (their jobs change without their record). The others are
kept as read, and everything is read again every ``rescan_seconds``.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
import uuid
from typing import Any

from schemas.experiments import RUN_ACTIVE, ExperimentRecord, RunState
from schemas.job import JobSpec
from schemas.records import JobStatus
from services.experiments import warm_start
from services.experiments.expand import job_document
from services.experiments.service import ExperimentService
from services.experiments.state import UnknownExperiment
from services.jobs.quotas import StorageQuota
from services.jobs.service import Caller, TooManyJobs
from services.jobs.state import Conflict, UnknownJob
from services.queue.base import JobQueue

log = logging.getLogger(__name__)

STALE_ADMISSION = 15.0
LOCK_KEY = "ndrf:experiment-scheduler"


class RedisLeader:
    """A renewable lease on one Redis key: the process holding it ticks."""

    def __init__(self, client: Any, ttl_seconds: float = 5.0, key: str = LOCK_KEY):
        self.client, self.key, self.ttl_ms = client, key, int(ttl_seconds * 1000)
        self.me = uuid.uuid4().hex

    def acquire(self) -> bool:
        try:
            if self.client.set(self.key, self.me, nx=True, px=self.ttl_ms):
                return True
            if self.client.get(self.key) == self.me:
                self.client.pexpire(self.key, self.ttl_ms)
                return True
        except Exception as exc:  # Redis away: skip this tick
            log.warning("experiment scheduler: lock unavailable (%s)", exc)
        return False


class Scheduler:
    def __init__(self, experiments: ExperimentService, queue: JobQueue, *, interval: float = 0.5,
                 leader: RedisLeader | None = None, rescan_seconds: float = 60.0):
        self.experiments, self.queue = experiments, queue
        self.states, self.jobs = experiments.states, experiments.jobs
        self.interval, self.leader, self.rescan_seconds = interval, leader, rescan_seconds
        self._bases: dict[str, dict] = {}
        self._served: dict[str, float] = {}
        self._read: dict[str, tuple[bytes, ExperimentRecord]] = {}   # by experiment: its marker when read, the record
        self._last_rescan = float("-inf")
        self.stopping = threading.Event()

    # ---------------------------------------------------------------- the loop

    def run(self) -> None:
        log.info("experiment scheduler started (every %.1f s)", self.interval)
        while not self.stopping.wait(self.interval):
            if self.leader is not None and not self.leader.acquire():
                continue
            try:
                self.tick()
            except Exception:  # the store or the queue briefly away: the next tick tries again
                log.exception("experiment scheduler tick failed")

    def start(self) -> threading.Thread:
        thread = threading.Thread(target=self.run, name="ndrf-experiment-scheduler", daemon=True)
        thread.start()
        return thread

    def stop(self) -> None:
        self.stopping.set()

    def tick(self) -> int:
        """Refresh every active experiment, then admit runs while the queue has nobody waiting.
        Returns how many runs were admitted."""
        self._rescan()
        open_: list[ExperimentRecord] = []
        marks = self.states.active_marks()
        for exp_id in set(self._read) - set(marks):
            self._read.pop(exp_id)
        for exp_id, mark in marks.items():
            read = self._read.get(exp_id)
            if read is not None and read[0] == mark and not self._moving(read[1]):
                open_.append(read[1])   # unchanged since it was read, and nothing of it in flight
                continue
            try:
                record = self.refresh(exp_id)
            except UnknownExperiment:
                self.states.unmark_active(exp_id)
                self._read.pop(exp_id, None)
                continue
            if record is not None:
                self._read[exp_id] = (mark, record)
                open_.append(record)
            else:
                self._read.pop(exp_id, None)
        admitted = 0
        for _ in range(64):
            if self.queue.depth().get("waiting", 0) > 0:
                break
            candidates = [r for r in open_ if self._has_slot(r)]
            if not candidates:
                break
            record = min(candidates, key=lambda r: (self._served.get(r.id, 0.0), r.id))
            self._served[record.id] = time.monotonic()
            try:
                fresh = self.admit(record.id)
            except UnknownExperiment:     # gone since it was read
                self._read.pop(record.id, None)
                fresh = None
            if fresh is None:
                open_ = [r for r in open_ if r.id != record.id]
                continue
            admitted += 1
            open_ = [fresh if r.id == fresh.id else r for r in open_]
            time.sleep(0.05)           # let an idle worker take it before looking at the queue again
        return admitted

    @staticmethod
    def _moving(record: ExperimentRecord) -> bool:
        """Whether the record may be out of date without a change of its own: a run being
        admitted (a stale admission to complete) or whose job is queued or running."""
        return any(run.status == "admitting" or (run.job and run.status in ("queued", "running"))
                   for run in record.runs)

    @staticmethod
    def _has_slot(record: ExperimentRecord) -> bool:
        if record.canceled:
            return False
        active = sum(run.status in RUN_ACTIVE for run in record.runs)
        return active < int(record.sweep.get("max_concurrent", 1)) and Scheduler._next(record) is not None

    @staticmethod
    def _next(record: ExperimentRecord) -> RunState | None:
        """The first pending run that may be admitted now (with a warm start: run 0 first, the
        others once it has succeeded)."""
        return next((r for r in record.runs if r.status == "pending" and warm_start.admissible(record, r)), None)

    def _rescan(self) -> None:
        """A safety net for markers: every ``rescan_seconds``, mark any unfinished experiment."""
        now = time.monotonic()
        if now - self._last_rescan < self.rescan_seconds:
            return
        self._last_rescan = now
        self._read.clear()   # every active experiment is read again at this tick
        active = set(self.states.active_ids())
        for record in self.states.records():
            if record.id not in active and not record.status.finished:
                self.states.mark_active(record.id)

    # ----------------------------------------------------------------- refresh

    def refresh(self, exp_id: str) -> ExperimentRecord | None:
        """Run statuses from the jobs' records; completes stale admissions. Returns the record,
        or None once the experiment has nothing left to do (its marker is removed)."""
        record = self.states.get(exp_id)
        observed: dict[int, str] = {}
        for run in record.runs:
            if run.status == "admitting" and (run.since is None or time.time() - run.since > STALE_ADMISSION):
                self._complete(record, run)
            elif run.job and run.status in ("queued", "running"):
                try:
                    status = self.jobs.states.get(run.job).status.value
                except (UnknownJob, ValueError):
                    status = JobStatus.FAILED.value      # deleted under the experiment
                if status != run.status:
                    observed[run.index] = status
        if observed or warm_start.skip_dependents(record.model_copy(deep=True)):
            events: list[dict] = []

            def change(current: ExperimentRecord) -> ExperimentRecord | None:
                for run in current.runs:
                    new = observed.get(run.index)
                    if new and run.status in ("queued", "running") and run.job == record.runs[run.index].job:
                        run.status = new  # type: ignore[assignment]
                        events.append({"type": "run", "index": run.index, "job": run.job, "status": new})
                events.extend(warm_start.skip_dependents(current))   # the warm-start source failed
                return current if events else None

            record, _ = self.states.update(exp_id, change, events)
        if record.status.finished and not any(r.status == "pending" or r.status in RUN_ACTIVE for r in record.runs):
            self.states.unmark_active(exp_id)
            again = self.states.get(exp_id)           # an append or a retry may have landed meanwhile
            if not again.status.finished:
                self.states.mark_active(exp_id)
                return again
            self._bases.pop(exp_id, None)
            return None
        return record

    # ------------------------------------------------------------------- admit

    def admit(self, exp_id: str) -> ExperimentRecord | None:
        """Reserve the next pending run under ``max_concurrent`` and submit its job. Returns the
        updated record, or None when the experiment had no free slot or pending run."""
        chosen: list[int] = []

        def reserve(record: ExperimentRecord) -> ExperimentRecord | None:
            chosen.clear()
            if not self._has_slot(record):
                return None
            run = self._next(record)
            assert run is not None  # _has_slot found one
            run.status, run.admissions, run.since = "admitting", run.admissions + 1, time.time()
            chosen.append(run.index)
            return record

        record, changed = self.states.update(exp_id, reserve)
        if not changed:
            return None
        return self._complete(record, record.runs[chosen[0]])

    def _complete(self, record: ExperimentRecord, run: RunState) -> ExperimentRecord | None:
        """Submit the job of a run being admitted and assign it; None if it could not be
        submitted now (the run is pending again, or another scheduler is on it)."""
        exp_id, index, admission = record.id, run.index, run.admissions
        base = self._bases.get(exp_id)
        if base is None:
            base = self._bases[exp_id] = self.states.base(exp_id)
        spec = JobSpec.model_validate(job_document(base, run.values))
        label = ", ".join(f"{k}={v}" for k, v in run.values.items())
        spec = spec.model_copy(update={"name": f"{record.name or exp_id} #{index}: {label}"[:200]})
        spec = warm_start.warm_spec(record, run, spec)
        try:
            job, _ = self.jobs.submit(spec, Caller(record.owner), f"experiment:{exp_id}:{index}:{admission}",
                                      max_active=self.experiments.limits.active_jobs_per_key,
                                      limits=self.experiments.limits, experiment=exp_id, varied=run.values)
        except (TooManyJobs, StorageQuota) as exc:   # the owner's caps: the run waits for room
            log.info("experiment %s run %d waits: %s", exp_id, index, exc)
            self._release(exp_id, index, admission)
            return None
        except Conflict as exc:          # another scheduler is submitting this very admission
            log.info("experiment %s run %d: %s", exp_id, index, exc)
            return None

        events: list[dict] = []

        def assign(current: ExperimentRecord) -> ExperimentRecord | None:
            target = current.runs[index]
            if target.status != "admitting" or target.admissions != admission:
                return None
            target.status, target.job = "queued", job.id
            if job.id not in target.jobs:
                target.jobs.append(job.id)
            events.append({"type": "run", "index": index, "job": job.id, "status": "queued"})
            return current

        updated, changed = self.states.update(exp_id, assign, events)
        if changed:
            log.info("experiment %s: run %d admitted as job %s", exp_id, index, job.id)
        elif updated.runs[index].job != job.id:  # canceled while being admitted: its job must not run
            with contextlib.suppress(Conflict, UnknownJob):
                self.jobs.cancel(job.id)
        return updated

    def _release(self, exp_id: str, index: int, admission: int) -> None:
        def release(current: ExperimentRecord) -> ExperimentRecord | None:
            target = current.runs[index]
            if target.status != "admitting" or target.admissions != admission:
                return None
            target.status, target.since = "pending", None
            return current

        self.states.update(exp_id, release)

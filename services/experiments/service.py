"""The experiment service: create, list, inspect, cancel, retry and append to experiments.

An experiment is a record of runs (:mod:`services.experiments.state`); each run becomes an
ordinary job (:class:`services.jobs.service.JobService.submit`, with the experiment's id and the
run's values on the job record) only when the scheduler (:mod:`services.experiments.scheduler`)
admits it under ``max_concurrent``. Creating an experiment therefore queues nothing by itself:
it validates every run (:mod:`services.experiments.validate`) and stores the record.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator

from schemas.experiments import (
    RUN_ACTIVE,
    ExperimentAppend,
    ExperimentPublic,
    ExperimentRecord,
    ExperimentSpec,
    Objective,
    RunRow,
    RunState,
)
from schemas.job import JobSpec
from schemas.records import JobRecord
from services.experiments import results, warm_start
from services.experiments.expand import InvalidExperiment, check_sweep, expand, job_document, merge
from services.experiments.state import (
    ExperimentConflict,
    ExperimentStates,
    UnknownExperiment,
    counts,
    new_experiment_id,
)
from services.experiments.validate import Preflight, check_run_count, validate_runs
from services.jobs.service import SYSTEM, Caller, JobService, scene_label
from services.jobs.state import Conflict, UnknownJob, now_iso
from services.queue.base import LockBusy
from services.settings import Limits

log = logging.getLogger(__name__)


class TooManyExperiments(Exception):
    """The key has ``experiments_per_key`` unfinished experiments (a 429)."""


def may_see(caller: Caller, record: ExperimentRecord) -> bool:
    return caller.admin or record.owner == caller.owner


def normalize(spec: ExperimentSpec) -> tuple[dict, dict]:
    """``(base job document, sweep)``: the sweep is the spec without its base and name, with the
    seed list resolved (``grid.seed`` is read as ``seeds``; no seeds = the base job's seed)."""
    if spec.base is None:
        raise InvalidExperiment("base_job", "the base job was not resolved (base_job is for the API)")
    base = spec.base.model_dump(mode="json")
    sweep = spec.model_dump(mode="json", exclude={"base", "base_job", "name"})
    grid = sweep["grid"]
    if "seed" in grid:
        if sweep.get("seeds"):
            raise InvalidExperiment("grid.seed", "give the seeds once: 'seeds' or grid.seed, not both")
        sweep["seeds"] = list(dict.fromkeys(grid.pop("seed")))
        if not all(isinstance(s, int) and 0 <= s <= 2**31 - 1 for s in sweep["seeds"]):
            raise InvalidExperiment("grid.seed", "seeds are integers in [0, 2^31 - 1]")
    sweep["seeds"] = sweep.get("seeds") or [base["seed"]]
    return base, sweep


class ExperimentService:
    def __init__(self, jobs: JobService, limits: Limits):
        self.jobs = jobs
        self.limits = limits
        self.states = ExperimentStates(jobs.store, jobs.events)

    # ------------------------------------------------------------------ reads

    def record(self, exp_id: str, caller: Caller = SYSTEM) -> ExperimentRecord:
        record = self.states.get(exp_id)
        if not may_see(caller, record):
            raise UnknownExperiment(exp_id)
        return record

    def records(self, caller: Caller = SYSTEM, before: str | None = None) -> Iterator[ExperimentRecord]:
        for exp_id in self.states.ids():
            if before is not None and exp_id >= before:
                continue
            try:
                record = self.states.get(exp_id)
            except (UnknownExperiment, ValueError):
                continue
            if may_see(caller, record):
                yield record

    def rows(self, record: ExperimentRecord) -> list[RunRow]:
        return [row for row, _ in self._rows_and_metrics(record)]

    def _rows_and_metrics(self, record: ExperimentRecord) -> list[tuple[RunRow, dict | None]]:
        target_error = float(record.sweep.get("target_error", 0.05))
        planned = record.base_iterations
        out = []
        for run in record.runs:
            job, metrics = self._job_and_metrics(record.id, run, target_error)
            out.append((results.run_row(run, job, metrics, planned), metrics))
        return out

    def _job_and_metrics(self, exp_id: str, run: RunState, target_error: float
                         ) -> tuple[JobRecord | None, dict | None]:
        if run.job is None:
            return None, None
        try:
            job = self.jobs.states.get(run.job)
        except (UnknownJob, ValueError):
            return None, None
        cached = self.states.cached_metrics(exp_id, run.job) if results.is_finished(job) else None
        if cached is not None and cached.get("target_error") == target_error:
            return job, cached
        metrics = results.job_metrics(self.jobs.states.files(run.job), job, target_error)
        if results.is_finished(job):
            self.states.cache_metrics(exp_id, run.job, metrics)
        return job, metrics

    def public(self, record: ExperimentRecord, *, read_token: str | None = None,
               detail: bool = True) -> ExperimentPublic:
        """The API document; with ``detail`` also the best run and the aggregates over seeds
        (which read every run's job), without it only counts (lists)."""
        rows = self.rows(record) if detail else []
        objective = Objective.model_validate(record.sweep.get("objective") or {})
        return ExperimentPublic(
            id=record.id, name=record.name, status=record.status, created=record.created, updated=record.updated,
            finished=record.finished, runs=len(record.runs), counts=counts(record),
            max_concurrent=int(record.sweep.get("max_concurrent", 1)), varied=record.varied, objective=objective,
            best=results.best_run(objective, rows) if detail else None, sweep=record.sweep,
            base_method=record.base_method, base_scene=record.base_scene,
            aggregates=results.aggregates(record, rows) if detail else None, read_token=read_token)

    def curves(self, record: ExperimentRecord) -> results.Curves:
        target_error = float(record.sweep.get("target_error", 0.05))
        return results.curves([(run, self._job_and_metrics(record.id, run, target_error)[1]) for run in record.runs])

    # ----------------------------------------------------------------- create

    def open_count(self, owner: str) -> int:
        """Unfinished experiments of ``owner``."""
        return sum(1 for r in self.records() if r.owner == owner and not r.status.finished)

    def create(self, spec: ExperimentSpec, caller: Caller = SYSTEM, preflight: Preflight | None = None,
               max_concurrent: int | None = None) -> ExperimentRecord:
        """Validate every run (:class:`InvalidExperiment` naming the run and field) and store the
        experiment; its runs are pending until the scheduler admits them. A key with
        ``experiments_per_key`` unfinished experiments is refused (:class:`TooManyExperiments`),
        counted and stored in one step under the key's lock."""
        self._check_open(caller.owner)
        base, sweep = normalize(spec)
        assert spec.base is not None
        if max_concurrent is not None:
            sweep["max_concurrent"] = max_concurrent
        varied = check_sweep(sweep, base)
        check_run_count(sweep, base, self.limits)
        planned = expand(sweep, base)
        warm_start.check_runs(sweep, validate_runs(base, planned, self.limits, preflight), None)
        now = now_iso()
        record = ExperimentRecord(id=new_experiment_id(), name=spec.name, owner=caller.owner, created=now,
                                  updated=now, sweep=sweep, varied=varied, base_method=str(spec.base.method),
                                  base_scene=scene_label(spec.base), base_iterations=spec.base.iterations,
                                  base_job=spec.base_job,
                                  runs=[RunState(index=i, key=p.key, values=p.values) for i, p in enumerate(planned)])
        try:
            with self.jobs.queue.hold(f"experiments:{caller.owner}"):
                self._check_open(caller.owner)
                self.states.create(record, base)
        except LockBusy:
            raise TooManyExperiments("other experiments of this key are being created: retry") from None
        log.info("experiment %s created: %d runs, %d at once", record.id, len(record.runs), sweep["max_concurrent"])
        return record

    def _check_open(self, owner: str) -> None:
        count, cap = self.open_count(owner), self.limits.experiments_per_key
        if count >= cap:
            raise TooManyExperiments(f"{count} experiments of this key are unfinished (limit {cap}, "
                                     f"NDRF_MAX_EXPERIMENTS_PER_KEY): cancel one or wait for it")

    # ------------------------------------------------------------ cancel/retry

    def cancel(self, exp_id: str, caller: Caller = SYSTEM) -> ExperimentRecord:
        """Pending runs are canceled at once; queued and running runs' jobs are canceled (a running
        job stops at its next training step and keeps its artifacts)."""
        self.record(exp_id, caller)

        def change(record: ExperimentRecord) -> ExperimentRecord | None:
            if record.status.finished:
                raise ExperimentConflict(f"experiment {exp_id} is already {record.status.value}")
            record.canceled = True
            for run in record.runs:
                if run.status in ("pending", "admitting"):
                    run.status = "canceled"
            return record

        record, _ = self.states.update(exp_id, change)
        for run in record.runs:
            if run.job and run.status in RUN_ACTIVE:
                with contextlib.suppress(Conflict, UnknownJob):   # it finished meanwhile: the scheduler records how
                    self.jobs.cancel(run.job)
        self.states.event(exp_id, {"type": "canceled", "note": "canceled by its owner"})
        return record

    def retry(self, exp_id: str, caller: Caller = SYSTEM) -> tuple[ExperimentRecord, list[int]]:
        """Put failed and canceled runs back to pending (each gets a new job when admitted);
        succeeded runs are not run again."""
        self.record(exp_id, caller)
        again: list[int] = []

        def change(record: ExperimentRecord) -> ExperimentRecord | None:
            again.clear()
            for run in record.runs:
                if run.status in ("failed", "canceled"):
                    run.status, run.job, run.since, run.error = "pending", None, None, None
                    again.append(run.index)
            if not again:
                raise ExperimentConflict(f"experiment {exp_id} has no failed or canceled runs to retry")
            record.canceled = False
            return record

        record, _ = self.states.update(exp_id, change)
        self.states.mark_active(exp_id)
        self.states.event(exp_id, {"type": "retry", "runs": again})
        return record, list(again)

    # ----------------------------------------------------------------- append

    def append(self, exp_id: str, more: ExperimentAppend, caller: Caller = SYSTEM,
               preflight: Preflight | None = None) -> tuple[ExperimentRecord, list[int]]:
        """Add the runs that more grid values, seeds or random draws make; runs that exist are
        kept as they are (a finished run is not run again). Reopens a canceled experiment for the
        new runs."""
        current = self.record(exp_id, caller)
        base = self.states.base(exp_id)
        sweep = merge(current.sweep, more.model_dump(mode="json"))
        check_run_count(sweep, base, self.limits)
        known = {run.key for run in current.runs}
        fresh = [p for p in expand(sweep, base) if p.key not in known]
        specs = validate_runs(base, fresh, self.limits, preflight, first_index=len(current.runs))
        if warm_start.settings(sweep) is not None and current.runs:
            source = JobSpec.model_validate(job_document(base, current.runs[warm_start.SOURCE].values))
            warm_start.check_runs(sweep, specs, source, first_index=len(current.runs))
        varied = check_sweep(sweep, base)
        added: list[int] = []

        def change(record: ExperimentRecord) -> ExperimentRecord | None:
            added.clear()
            have = {run.key for run in record.runs}
            for planned in fresh:
                if planned.key not in have:
                    added.append(len(record.runs))
                    record.runs.append(RunState(index=len(record.runs), key=planned.key, values=planned.values))
            record.sweep, record.varied = sweep, varied
            if added:
                record.canceled = False
            return record

        record, _ = self.states.update(exp_id, change)
        if added:
            self.states.mark_active(exp_id)
            self.states.event(exp_id, {"type": "appended", "runs": list(added)})
        return record, list(added)


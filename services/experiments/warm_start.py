"""An experiment's warm start (``warm_start: "first_run"``): run 0 runs cold, every other run
starts from run 0's trained fields.

Pure decisions over the experiment record; the scheduler (:mod:`services.experiments.scheduler`)
applies them:

* a run other than the source is *admissible* only once the source run has **succeeded** (its
  final checkpoint holds the fields trained to its last iteration); before that it stays
  ``pending`` and does not hold a slot under ``max_concurrent``;
* when the source run failed or was canceled, every pending run that depends on it fails
  without a job (:func:`skip_dependents`, with ``RunState.error`` saying why); ``retry`` puts
  them all back to pending, and run 0 runs first again;
* the job of a dependent run is the run's job document with ``warm_start: {job: <run 0's job>,
  parameters, top_up_steps}`` (:func:`warm_spec`); the host checks it like any job-level warm
  start (:mod:`services.jobs.warm_start`), the child records what was reused in ``plan.json``
  (``warm_start``), which the experiment's rows and ``results.csv`` show.

At creation (:func:`check_runs`) every dependent run must be warm-startable from run 0: the same
scene, parameter keys, field settings and effect overrides, a method that trains fields, and no
``warm_start`` of its own.
"""

from __future__ import annotations

from collections.abc import Sequence

from schemas.experiments import ExperimentRecord, RunState
from schemas.job import JobSpec, WarmStart
from schemas.methods import Method
from services.experiments.expand import InvalidExperiment
from services.jobs.warm_start import mismatch

#: The run every other run warm-starts from.
SOURCE = 0
#: Methods that train no field: nothing to warm-start from or into.
FIELDLESS = frozenset({Method.PRB, Method.DIRECT})


def settings(record_or_sweep: ExperimentRecord | dict) -> dict | None:
    """The experiment's ``warm_start`` settings, or None when its runs run cold."""
    sweep = record_or_sweep.sweep if isinstance(record_or_sweep, ExperimentRecord) else record_or_sweep
    return sweep.get("warm_start") or None


def admissible(record: ExperimentRecord, run: RunState) -> bool:
    """Whether the pending ``run`` may be admitted now."""
    if settings(record) is None or run.index == SOURCE:
        return True
    return record.runs[SOURCE].status == "succeeded" and record.runs[SOURCE].job is not None


def skip_dependents(record: ExperimentRecord) -> list[dict]:
    """Fail the pending runs whose source run failed or was canceled (in place); the events."""
    source = record.runs[SOURCE] if record.runs else None
    if settings(record) is None or source is None or source.status not in ("failed", "canceled"):
        return []
    why = f"not run: run {SOURCE} (the warm-start source) {source.status}"
    events = []
    for run in record.runs:
        if run.index != SOURCE and run.status == "pending":
            run.status, run.error = "failed", why
            events.append({"type": "run", "index": run.index, "job": None, "status": "failed", "note": why})
    return events


def warm_spec(record: ExperimentRecord, run: RunState, spec: JobSpec) -> JobSpec:
    """``spec`` (the run's job) warm-started from the source run's job; unchanged for the source
    run and for experiments without a warm start."""
    warm = settings(record)
    if warm is None or run.index == SOURCE:
        return spec
    source_job = record.runs[SOURCE].job
    assert source_job is not None  # admissible() admits dependents only after the source succeeded
    return spec.model_copy(update={"warm_start": WarmStart(job=source_job, parameters=bool(warm.get("parameters")),
                                                           top_up_steps=warm.get("top_up_steps"))})


def check_runs(sweep: dict, specs: Sequence[JobSpec], source: JobSpec | None, first_index: int = 0) -> None:
    """Every run of ``specs`` (run indices from ``first_index``) can warm-start from ``source``
    (run 0's job; ``specs[0]`` when None); :class:`InvalidExperiment` naming the run otherwise."""
    if settings(sweep) is None or not specs:
        return
    source = source or specs[0]
    for offset, spec in enumerate(specs):
        index = first_index + offset
        if spec.warm_start is not None:
            raise InvalidExperiment(f"runs[{index}].warm_start", "the experiment's warm_start sets each run's "
                                                                 "warm_start: leave it out of the base job")
        if spec.method in FIELDLESS:
            raise InvalidExperiment(f"runs[{index}].method", f"{spec.method} trains no field: there is nothing to "
                                                             f"warm-start (warm_start needs an ndrf-* or "
                                                             f"radiance-cache method)")
        if index == SOURCE:
            continue
        reason = mismatch(spec, source, f"of run {SOURCE}")
        if reason is not None:
            raise InvalidExperiment(f"runs[{index}].warm_start", f"run {index} cannot warm-start from run "
                                                                 f"{SOURCE}: {reason}")

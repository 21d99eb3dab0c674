"""What an experiment's runs measured: run rows, ``results.csv``, mean and spread over seeds per
configuration, the best run, and accuracy against time.

Everything is derived from the runs' own job files (record, plan, per-iteration records); nothing
is copied into the experiment while it runs. Time is *compute seconds*: the phases of each
iteration summed (training, warm-up included, rendering, gradient), cumulative over the
iterations, so that methods are compared on what they cost, not on how long they waited in the
queue or how busy the machine was with other runs' start-up. The parameter error after
iteration k is ``max |updated parameters - target|`` (synthetic targets only). A finished job's
metrics never change, so they are cached beside the experiment (``metrics/<job>.json``).
"""

from __future__ import annotations

import csv
import io
import json
import math
import re
import statistics
from collections.abc import Iterable
from datetime import UTC, datetime
from typing import Any

from schemas.experiments import (
    Aggregate,
    BestRun,
    Curve,
    Curves,
    ExperimentRecord,
    Objective,
    RunRow,
    RunState,
    finite_or_none,
)
from schemas.records import FINISHED, JobRecord
from services.experiments.expand import SEED, run_key
from services.store.job import JobFiles

METRICS = ("final_loss", "final_parameter_error", "seconds", "time_to_error")
OBJECTIVE_COLUMN = {"parameter_error": "final_parameter_error", "loss": "final_loss", "seconds": "seconds",
                    "time_to_error": "time_to_error"}


def job_metrics(files: JobFiles, record: JobRecord, target_error: float) -> dict[str, Any]:
    """Curves and final values of one job from its files."""
    plan = files.read(JobFiles.PLAN) or {}
    target = plan.get("target_values")
    seconds, errors, losses = [], [], []
    reused = plan.get("warm_start")
    # a warm start's top-up trains before iteration 0 (a cold run's warm-up is in iteration 0's
    # training seconds): it counts, so that warm and cold runs are compared on what they cost
    top_up = float((reused or {}).get("top_up_seconds") or 0.0)
    total = top_up
    for k in files.iterations():
        item = files.iteration_record(k)
        if item is None:
            continue
        total += sum(float(v) for v in (item.get("seconds") or {}).values())
        seconds.append(total)
        losses.append(finite_or_none(item.get("loss")))
        answer = item.get("estimate") or item.get("updated_parameters")   # the answer had the run ended there
        errors.append(_max_abs(answer, target))
    initial = _max_abs(plan.get("init"), target)
    reached = next((t for t, e in zip(seconds, errors) if e is not None and e <= target_error), None)
    if reached is None and initial is not None and initial <= target_error:
        reached = 0.0
    return {"iterations": len(seconds), "seconds": seconds, "parameter_error": errors, "loss": losses,
            "initial_error": initial, "final_loss": losses[-1] if losses else None,
            "final_parameter_error": errors[-1] if errors else initial,
            "total_seconds": total if seconds else None, "time_to_error": reached,
            "wall_seconds": wall_seconds(record), "target_error": target_error, "warm_start": reused}


def _max_abs(values, target) -> float | None:
    if not values or not target or len(values) != len(target):
        return None
    return max(abs(float(v) - float(t)) for v, t in zip(values, target))


def wall_seconds(record: JobRecord) -> float | None:
    if record.started is None:
        return None
    try:
        start = datetime.fromisoformat(record.started)
        end = datetime.fromisoformat(record.finished) if record.finished else datetime.now(UTC)
    except ValueError:
        return None
    return max(0.0, (end - start).total_seconds())


def run_row(run: RunState, record: JobRecord | None, metrics: dict | None, planned: int | None) -> RunRow:
    varied = {k: v for k, v in run.values.items() if k != SEED}
    row = RunRow(index=run.index, job=run.job, status=run.status, varied=varied, seed=run.values.get(SEED),
                 iterations_planned=planned, attempts=len(run.jobs))
    if record is not None:
        row.status = record.status.value if run.status not in ("pending", "admitting") else run.status
        row.iterations_planned = record.iterations
        row.error = record.error
    elif run.error:
        row.error = run.error
    if metrics:
        row.iterations = metrics["iterations"]
        row.final_loss = metrics["final_loss"]
        row.final_parameter_error = metrics["final_parameter_error"]
        row.seconds = metrics["total_seconds"]
        row.wall_seconds = metrics["wall_seconds"]
        row.time_to_error = metrics["time_to_error"]
        row.warm_start = metrics.get("warm_start")
    return row


def configuration_of(values: dict[str, Any]) -> dict[str, Any]:
    return {k: v for k, v in values.items() if k != SEED}


def aggregates(record: ExperimentRecord, rows: Iterable[RunRow]) -> list[Aggregate]:
    """Mean, sample standard deviation, min and max over the succeeded runs of each
    configuration (the run values but the seed), in run order."""
    groups: dict[str, list[RunRow]] = {}
    configurations: dict[str, dict] = {}
    for row in rows:
        key = run_key(row.varied)
        groups.setdefault(key, []).append(row)
        configurations.setdefault(key, row.varied)
    out = []
    for key, members in groups.items():
        done = [r for r in members if r.status == "succeeded"]
        metrics = {}
        for name in METRICS:
            values = [v for v in (getattr(r, name) for r in done) if v is not None and math.isfinite(v)]
            metrics[name] = {"mean": statistics.fmean(values) if values else None,
                             "std": statistics.stdev(values) if len(values) > 1 else None,
                             "min": min(values) if values else None, "max": max(values) if values else None,
                             "n": float(len(values))}
        out.append(Aggregate(configuration=configurations[key], runs=len(members), succeeded=len(done),
                             metrics=metrics))
    return out


def best_run(objective: Objective, rows: Iterable[RunRow]) -> BestRun | None:
    column = OBJECTIVE_COLUMN[objective.metric]
    scored = [(getattr(r, column), r) for r in rows if r.status == "succeeded" and getattr(r, column) is not None]
    if not scored:
        return None
    pick = min if objective.goal == "min" else max
    value, row = pick(scored, key=lambda item: item[0])
    return BestRun(index=row.index, job=row.job, varied={**row.varied, SEED: row.seed}, value=value)


def results_csv(rows: list[RunRow]) -> str:
    """One line per run: index, job, status, seed, every varied field, then the measurements."""
    fields: list[str] = []
    for row in rows:
        fields += [k for k in row.varied if k not in fields]
    head = ["run", "job", "status", "seed", *fields, "iterations", "iterations_planned", "final_loss",
            "final_parameter_error", "seconds", "wall_seconds", "time_to_error", "attempts", "error",
            "warm_start_job", "top_up_steps"]
    buffer = io.StringIO()
    writer = csv.writer(buffer, lineterminator="\n", quoting=csv.QUOTE_MINIMAL)   # separators, quotes, CR/LF quoted
    writer.writerow([escape_cell(cell) for cell in head])
    for row in rows:
        varied = [_cell(row.varied.get(k)) for k in fields]
        writer.writerow([row.index, escape_cell(row.job or ""), row.status, _cell(row.seed), *varied, row.iterations,
                         _cell(row.iterations_planned), _cell(row.final_loss), _cell(row.final_parameter_error),
                         _cell(row.seconds), _cell(row.wall_seconds), _cell(row.time_to_error), row.attempts,
                         escape_cell(row.error or ""), escape_cell((row.warm_start or {}).get("job") or ""),
                         _cell((row.warm_start or {}).get("top_up_steps"))])
    return buffer.getvalue()


#: Characters with which a spreadsheet starts a formula (OWASP, "CSV Injection").
FORMULA_STARTS = ("=", "+", "-", "@", "\t", "\r")
_NUMBER = re.compile(r"[+-]?(?:\d+\.?\d*|\.\d+)(?:[eE][+-]?\d+)?")


def escape_cell(value: Any) -> Any:
    """A CSV cell a spreadsheet will not run as a formula (OWASP's recommendation): text that starts
    with ``=``, ``+``, ``-``, ``@``, a tab or a carriage return gets a leading single quote. Numbers
    (and text that is exactly a number, such as ``-0.5``) are left as they are; the writer quotes
    separators, quotes and line breaks."""
    if not isinstance(value, str) or not value.startswith(FORMULA_STARTS) or _NUMBER.fullmatch(value):
        return value
    return "'" + value


def _cell(value: Any) -> str:
    if value is None:
        return ""
    if isinstance(value, float):
        return repr(value)
    if isinstance(value, int):
        return str(value)
    if isinstance(value, str):
        return escape_cell(value)
    return escape_cell(json.dumps(value, separators=(",", ":")))


def curves(runs: list[tuple[RunState, dict | None]]) -> Curves:
    """Per run, and per configuration the mean over its seeds (cut to the shortest run), with the
    [min, max] of the parameter error per point."""
    per_run: list[Curve] = []
    groups: dict[str, tuple[dict, list[tuple[RunState, dict]]]] = {}
    for run, metrics in runs:
        if not metrics or not metrics["iterations"]:
            continue
        varied = configuration_of(run.values)
        per_run.append(Curve(label=f"#{run.index}", varied={**varied, SEED: run.values.get(SEED)}, runs=[run.index],
                             seconds=metrics["seconds"], parameter_error=metrics["parameter_error"],
                             loss=metrics["loss"], initial_parameter_error=metrics.get("initial_error")))
        groups.setdefault(run_key(varied), (varied, []))[1].append((run, metrics))
    configurations = []
    for varied, members in groups.values():
        length = min(m["iterations"] for _, m in members)
        seconds = [statistics.fmean(m["seconds"][k] for _, m in members) for k in range(length)]
        errors, spread, losses = [], [], []
        for k in range(length):
            point = [m["parameter_error"][k] for _, m in members if m["parameter_error"][k] is not None]
            errors.append(statistics.fmean(point) if point else None)
            spread.append([min(point), max(point)] if point else [])
            loss = [m["loss"][k] for _, m in members if m["loss"][k] is not None]
            losses.append(statistics.fmean(loss) if loss else None)
        label = ", ".join(f"{k}={json.dumps(v) if not isinstance(v, str) else v}" for k, v in varied.items()) or "base"
        initial = [m["initial_error"] for _, m in members if m.get("initial_error") is not None]
        configurations.append(Curve(label=label, varied=varied, runs=[r.index for r, _ in members], seconds=seconds,
                                    parameter_error=errors, parameter_error_spread=spread, loss=losses,
                                    initial_parameter_error=statistics.fmean(initial) if initial else None))
    return Curves(runs=per_run, configurations=configurations)


def is_finished(record: JobRecord) -> bool:
    return record.status in FINISHED

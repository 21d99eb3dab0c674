"""How store records become API documents (pure functions over the job folder)."""

from __future__ import annotations

import numpy as np

from schemas.records import FINISHED, JobPublic
from services.store.layout import JobFolder


def _labels(plan: dict) -> list[str]:
    return plan.get("scalars") or []


def job_public(folder: JobFolder) -> JobPublic:
    record = folder.read("record.json")
    plan = folder.read("plan.json")
    labels = _labels(plan or {})
    latest = folder.iteration_record(record["iteration"]) if record.get("iteration") is not None else None
    values = latest["updated_parameters"] if latest else (plan or {}).get("init")
    target = (plan or {}).get("target_values")
    metrics = None
    if latest:
        metrics = {k: latest.get(k) for k in ("loss", "residual_primal", "residual_differential", "seconds",
                                               "sanitized", "parameter_error", "learning_rate") if k in latest}
    elapsed = eta = None
    if record.get("started"):
        done = [folder.iteration_record(k) for k in folder.iterations()[-5:]]
        per_iteration = [sum(r["seconds"].values()) for r in done if r]
        elapsed = _elapsed(record)
        if per_iteration and record["status"] not in FINISHED:
            remaining = record["iterations"] - (record["iteration"] + 1 if record.get("iteration") is not None else 0)
            eta = float(np.mean(per_iteration)) * max(remaining, 0)
    return JobPublic(
        id=record["id"], name=record.get("name"), status=record["status"], method=record["method"],
        scene=record["scene"], created=record["created"], updated=record.get("updated", record["created"]),
        iteration=record.get("iteration"), iterations=record["iterations"], attempts=record.get("attempts", 0),
        parameters=dict(zip(labels, values)) if labels and values else None,
        target=dict(zip(labels, target)) if labels and target else None,
        metrics=metrics, plan=plan, error=record.get("error"), field=record.get("field"),
        elapsed_seconds=elapsed, eta_seconds=eta,
    )


def _elapsed(record: dict) -> float | None:
    from datetime import datetime, timezone

    try:
        start = datetime.fromisoformat(record["started"])
        end = datetime.fromisoformat(record["updated"]) if record["status"] in FINISHED else datetime.now(timezone.utc)
    except (KeyError, ValueError):
        return None
    return max(0.0, (end - start).total_seconds())

"""How store records become API documents (pure functions over a job's record and files)."""

from __future__ import annotations

from datetime import UTC, datetime

import numpy as np

from api import tokens
from schemas.records import FINISHED, JobPublic, JobRecord
from services.settings import Settings
from services.store.job import JobFiles

METRICS = ("loss", "residual_radiance", "residual_differential", "seconds", "sanitized", "parameter_error", "views",
           "optimizer", "learning_rate", "textures", "estimate_error", "estimate_window")


def job_public(record: JobRecord, files: JobFiles, settings: Settings, *, mint_token: bool = True) -> JobPublic:
    """The job as the API shows it; ``mint_token`` false (a token-authenticated request): no new read token."""
    plan = files.read(JobFiles.PLAN) or {}
    labels = plan.get("scalars") or []
    latest = files.iteration_record(record.iteration) if record.iteration is not None else None
    values = (latest.get("estimate") or latest["updated_parameters"]) if latest else plan.get("init")
    errors = latest.get("standard_error") if latest else None
    target = plan.get("target_values")
    estimate = dict(zip(labels, values)) if labels and values else None
    truth = dict(zip(labels, target)) if labels and target else None
    metrics = {k: latest.get(k) for k in METRICS if k in latest} if latest else None
    elapsed = eta = None
    if record.started:
        elapsed = _elapsed(record)
        if record.status not in FINISHED and record.iteration is not None:
            recent = [files.iteration_record(k) for k in range(max(0, record.iteration - 4), record.iteration + 1)]
            per_iteration = [sum(r["seconds"].values()) for r in recent if r]
            if per_iteration:
                eta = float(np.mean(per_iteration)) * max(record.iterations - record.iteration - 1, 0)
    token = (tokens.sign(settings.signing_secret(), record.id, settings.token_seconds)
             if settings.auth and mint_token else None)
    return JobPublic(
        id=record.id, name=record.name, status=record.status, method=record.method, scene=record.scene,
        created=record.created, updated=record.updated, iteration=record.iteration, iterations=record.iterations,
        attempts=record.attempts, estimate=estimate, parameters=estimate,
        standard_error=dict(zip(labels, errors)) if labels and errors else None,
        target_values=truth, target=truth, metrics=metrics, plan=plan or None,
        error=record.error, field=record.field, elapsed_seconds=elapsed, eta_seconds=eta,
        experiment=record.experiment, varied=record.varied, read_token=token,
        images_requested=record.images_requested,
    )


def _elapsed(record: JobRecord) -> float | None:
    if record.started is None:
        return None
    try:
        start = datetime.fromisoformat(record.started)
        end = datetime.fromisoformat(record.updated) if record.status in FINISHED else datetime.now(UTC)
    except (TypeError, ValueError):
        return None
    return max(0.0, (end - start).total_seconds())

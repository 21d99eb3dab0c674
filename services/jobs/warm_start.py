"""Warm starts on the host: a job's ``warm_start.job`` resolved to that job's checkpoint bytes,
within the tenant (the key's owner) only, and refused naming the mismatch unless the two jobs
share the scene and the parameter keys (and the fields' shapes: their settings and the effect
overrides). The solver loads the bytes (:mod:`services.solver.optimize.warm_start`).

A tenant never warm-starts from another tenant's job: the source's owner must equal the job's
owner, at submission and again when the attempt starts (an admin key included: its own jobs
only). A job another tenant owns is reported as unknown (its id is not confirmed).
"""

from __future__ import annotations

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.records import JobRecord
from services.jobs.state import JobStates, UnknownJob
from services.store.job import JobFiles

FIELD = "warm_start.job"


def mismatch(spec: JobSpec, source: JobSpec, source_id: str) -> str | None:
    """Why ``source`` (job ``source_id``) cannot warm-start ``spec``; None when it can."""
    if source.scene != spec.scene:
        ours, theirs = (getattr(s.scene, "builtin", None) or type(s.scene).__name__ for s in (spec, source))
        detail = f"{ours!r} here, {theirs!r} there" if ours != theirs else "its XML or files differ"
        return f"job {source_id} has another scene ({detail})"
    ours_keys, their_keys = [p.key for p in spec.parameters], [p.key for p in source.parameters]
    if ours_keys != their_keys:
        return f"job {source_id} recovers other parameter keys ({their_keys}; this job: {ours_keys})"
    for name in ("radiance", "differential"):
        if getattr(spec.training, name) != getattr(source.training, name):
            return f"job {source_id} has other training.{name} settings (the field's shape)"
    if spec.effects != source.effects:
        return f"job {source_id} has other effects overrides (the differential field's outputs)"
    return None


def source_checkpoint(states: JobStates, spec: JobSpec, owner: str, *, read: bool = True) -> bytes | None:
    """The checkpoint bytes of ``spec``'s warm-start source, a job of ``owner``; None without a
    warm start (or with ``read`` false: only checked). Raises :class:`InvalidJob` (field
    ``warm_start.job``) naming why not."""
    if spec.warm_start is None:
        return None
    source_id = spec.warm_start.job
    try:
        record: JobRecord = states.get(source_id)
    except (UnknownJob, ValueError):
        record = None  # type: ignore[assignment]
    if record is None or record.owner != owner:
        raise InvalidJob(FIELD, f"no job {source_id!r} of this API key")
    files = states.files(source_id)
    stored = files.read(JobFiles.SPEC)
    if stored is None:
        raise InvalidJob(FIELD, f"job {source_id} has no job file")
    reason = mismatch(spec, JobSpec.model_validate(stored), source_id)
    if reason is not None:
        raise InvalidJob(FIELD, reason)
    key = files.key(JobFiles.CHECKPOINT)
    blob = files.store.get(key) if read else None
    if (blob is None) if read else not files.store.exists(key):
        raise InvalidJob(FIELD, f"job {source_id} has no checkpoint yet (its fields are saved with the first one)")
    return blob

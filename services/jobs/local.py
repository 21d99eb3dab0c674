"""A job run in this process, into a job folder of its own (``ndrf run JOB.json --out DIR``).

The same record, states, writer and folder layout as the service, without a queue or a sandbox:
the job file and its scene are the user's own (a local ``{"path": ...}`` scene is allowed here).
An uploaded-style scene (``{"xml": ..., "files": ...}``) still goes through the upload checks.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from pathlib import Path

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.outcomes import Outcome
from schemas.records import JobRecord, JobStatus
from schemas.summary import Summary
from services.jobs.artifacts import JobWriter
from services.jobs.preflight import upload_limits
from services.jobs.service import scene_label
from services.jobs.state import JobStates, now_iso
from services.jobs.warm_start import source_checkpoint
from services.queue.base import EventBus
from services.settings import Limits
from services.store.job import JobFiles
from services.store.local import FolderStore
from services.uploads.staging import stage_job

log = logging.getLogger(__name__)


class OutFolderInUse(Exception):
    """``--out`` holds another job, or a finished run of this one (without ``--resume``)."""


class _Callback(EventBus):
    def __init__(self, on_event: Callable[[dict], None]):
        self.on_event = on_event

    def publish(self, job_id: str, event: dict) -> None:
        self.on_event(event)

    def wait(self, job_id: str, after_seq: int, timeout: float) -> bool:
        return False

    async def wait_async(self, job_id: str, after_seq: int, timeout: float) -> bool:
        return False


def run_local(spec: JobSpec, out: Path, *, base_dir: Path | None = None, resume: bool = False,
              on_event: Callable[[dict], None] = lambda event: None,
              should_stop: Callable[[], str | None] = lambda: None) -> dict:
    """Run ``spec`` to its end in ``out``; returns the summary (``summary.json``)."""
    from services.solver.optimize.loop import InverseRenderingRun

    out = out.resolve()
    states = JobStates(FolderStore(out.parent), _Callback(on_event))
    job_id = out.name
    files = states.files(job_id)
    attempt = _claim(states, files, spec, resume)
    writer = JobWriter(states, job_id, attempt=attempt, stop=should_stop)
    try:
        scene_file = stage_job(spec, out / "scene", upload_limits(Limits()), base_dir)
    except InvalidJob as exc:
        writer.finish({"status": "failed", "iterations": 0, "seconds": 0.0, "error": str(exc), "field": exc.field})
        return Summary.read(files.read(JobFiles.SUMMARY)).model_dump()
    checkpoint = files.resume_checkpoint() if resume else None
    try:  # a job folder beside this one (the same store, the same local owner)
        warm = source_checkpoint(states, spec, "local") if checkpoint is None else None
    except InvalidJob as exc:
        writer.finish({"status": "failed", "iterations": 0, "seconds": 0.0, "error": str(exc), "field": exc.field})
        return Summary.read(files.read(JobFiles.SUMMARY)).model_dump()
    outcome = InverseRenderingRun(spec, writer, scene_file=scene_file, resume=checkpoint, warm=warm).execute()
    writer.finish(outcome)
    if outcome.status == Outcome.INTERRUPTED:   # no summary.json: the job goes on from its checkpoint
        return Summary(status=outcome.status, iterations=outcome.iterations, seconds=outcome.seconds).model_dump()
    return Summary.read(files.read(JobFiles.SUMMARY)).model_dump()


def _claim(states: JobStates, files: JobFiles, spec: JobSpec, resume: bool) -> str:
    """Create the folder's record (or take over its own run with ``resume``) and claim it."""
    stored = files.read(JobFiles.SPEC)
    if stored is not None and JobSpec.model_validate(stored).fingerprint() != spec.fingerprint():
        raise OutFolderInUse(f"{files.job_id}/ holds another job; choose another --out")
    record = None
    if files.exists(JobFiles.RECORD):
        record = states.get(files.job_id)
        if record.status is not JobStatus.QUEUED and not resume:
            raise OutFolderInUse(f"{files.job_id}/ already holds a {record.status.value} run; "
                                 f"use --resume or another --out")
    else:
        files.write(JobFiles.SPEC, spec.model_dump(mode="json"))
        now = now_iso()
        record = states.create(JobRecord(id=files.job_id, name=spec.name, owner="local", status=JobStatus.QUEUED,
                                         method=str(spec.method), scene=scene_label(spec), created=now, updated=now,
                                         iterations=spec.iterations, fingerprint=spec.fingerprint()))
    attempt = f"local#{record.attempts + 1}"
    states.transition(files.job_id, JobStatus.RUNNING, attempt=attempt, attempts=record.attempts + 1, error=None,
                      field=None)
    return attempt

"""``/v1/jobs``: submit, list, inspect and cancel inverse-rendering jobs."""

from __future__ import annotations

import asyncio
import logging
import tempfile
import threading
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Header, Query, Response

from api.deps import Authenticated, RuntimeDep
from api.problems import Problem, ProblemError
from api.views import job_public
from schemas.job import JobSpec
from schemas.records import JobAccepted, JobPage, JobPublic, JobStatus
from services.errors import JobError
from services.jobs import JobConflict, UnknownJob
from services.limits import check_limits

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], dependencies=[Authenticated],
                   responses={401: {"model": Problem, "description": "Missing or wrong API key."}})

_preflight_lock = threading.Lock()  # one scene load at a time in the API process


def folder_or_404(runtime, job_id: str):
    try:
        return runtime.service.folder(job_id)
    except UnknownJob:
        raise ProblemError(404, "Not found", f"no job {job_id!r}", slug="unknown-job") from None


def _validate(spec: JobSpec, runtime) -> None:
    """Caps, then the solver's own preflight: the sandbox of uploaded files, the scene loads, the
    keys exist, targets decode and fit the films. Raises JobError naming the field."""
    limits = runtime.settings.limits
    check_limits(spec, limits)
    from services.optimize.setup import preflight
    from services.scene.sandbox import UploadLimits

    upload = UploadLimits(max_file_bytes=limits.mesh_bytes, max_total_bytes=limits.upload_bytes)
    with _preflight_lock, tempfile.TemporaryDirectory(prefix="ndrf-preflight-") as tmp:
        preflight(spec, folder=Path(tmp) / "scene", max_scalars=limits.parameters, upload_limits=upload)


@router.post("", status_code=202, response_model=JobAccepted,
             responses={409: {"model": Problem}, 413: {"model": Problem}, 422: {"model": Problem}},
             summary="Submit a job")
async def submit_job(spec: JobSpec, response: Response, runtime: RuntimeDep,
                     idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key", max_length=200,
                                                                   description="Retrying with the same key returns "
                                                                               "the same job.")] = None):
    """Validate a job (schema, caps, sandbox, scene and targets) and queue it. Answers ``202`` with
    the job id and a ``Location`` header; a bad job is a ``422`` naming the field."""
    service = runtime.service
    if idempotency_key:
        existing = service.find_idempotent(idempotency_key)
        if existing is not None:
            record = service.record(existing)
            if record.get("fingerprint") not in (None, spec.fingerprint()):
                raise ProblemError(409, "Conflict", "this Idempotency-Key was used for a different job",
                                   slug="idempotency-conflict")
            return _accepted(response, existing, record["status"])
    try:
        await asyncio.to_thread(_validate, spec, runtime)
    except JobError as exc:
        raise ProblemError(422, "Invalid job", str(exc), slug="invalid-job", errors=[(exc.field, exc.message)]) from None
    try:
        job_id, _ = service.submit(spec, idempotency_key, fingerprint=spec.fingerprint())
    except JobConflict as exc:
        raise ProblemError(409, "Conflict", str(exc), slug="idempotency-conflict") from None
    return _accepted(response, job_id, service.record(job_id)["status"])


def _accepted(response: Response, job_id: str, status: str) -> JobAccepted:
    base = f"/v1/jobs/{job_id}"
    response.headers["Location"] = base
    return JobAccepted(id=job_id, status=status, links={"self": base, "events": f"{base}/events",
                                                        "iterations": f"{base}/iterations", "cancel": f"{base}/cancel"})


@router.get("", response_model=JobPage, summary="List jobs")
def list_jobs(runtime: RuntimeDep,
              status: Annotated[JobStatus | None, Query(description="Only jobs with this status.")] = None,
              limit: Annotated[int, Query(ge=1, le=200, description="Page size.")] = 50,
              cursor: Annotated[str | None, Query(pattern="^[0-9a-f]{20}$", description="From a previous page.")] = None):
    """Jobs, newest first, ``limit`` per page."""
    items, next_cursor = [], None
    for record in runtime.service.records(status):
        if cursor is not None and record["id"] >= cursor:
            continue
        if len(items) == limit:
            next_cursor = items[-1].id
            break
        items.append(job_public(runtime.service.folder(record["id"])))
    return JobPage(items=items, next_cursor=next_cursor)


@router.get("/{job_id}", response_model=JobPublic, responses={404: {"model": Problem}}, summary="A job")
def get_job(job_id: str, runtime: RuntimeDep):
    """Status, current iteration, latest parameters and metrics, plan, error."""
    return job_public(folder_or_404(runtime, job_id))


@router.post("/{job_id}/cancel", status_code=202, response_model=JobPublic,
             responses={404: {"model": Problem}, 409: {"model": Problem}}, summary="Cancel a job")
def cancel_job(job_id: str, runtime: RuntimeDep):
    """A queued job is canceled at once; a running one stops at its next iteration boundary and
    keeps its artifacts. Canceling a finished job is a ``409``."""
    folder_or_404(runtime, job_id)
    try:
        runtime.service.cancel(job_id)
    except JobConflict as exc:
        raise ProblemError(409, "Conflict", str(exc), slug="job-finished") from None
    return job_public(runtime.service.folder(job_id))

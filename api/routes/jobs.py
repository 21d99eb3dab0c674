"""``/v1/jobs``: submit, list, inspect, cancel and delete inverse-rendering jobs."""

from __future__ import annotations

import logging
from typing import Annotated

import anyio
from fastapi import APIRouter, Header, Query, Request, Response

from api.bodies import GuardedRoute
from api.deps import CallerDep, ReaderDep, RuntimeDep, SettingsDep, may_mint_token
from api.problems import ProblemDetails, ProblemError, conflict
from api.views import job_public
from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.records import JobAccepted, JobPage, JobPublic, JobStatus
from services.jobs.preflight import preflight
from services.jobs.quotas import StorageQuota
from services.jobs.service import TooManyJobs
from services.jobs.warm_start import source_checkpoint
from services.runtime import Runtime

log = logging.getLogger(__name__)

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], route_class=GuardedRoute,
                   responses={401: {"model": ProblemDetails, "description": "Missing or wrong API key."}})


async def validate_job(spec: JobSpec, runtime: Runtime, owner: str) -> None:
    """Caps, sandbox, and the scene loaded in a sandboxed child (a 422 naming the field), in the
    key's line of admission work (:mod:`api.admission`)."""
    try:
        await runtime.admission.run(owner, preflight, spec, runtime.settings.limits)
    except InvalidJob as exc:
        raise ProblemError(422, "Invalid job", str(exc), slug="invalid-job", errors=[(exc.field, exc.message)]) from None


@router.post("", status_code=202, response_model=JobAccepted,
             responses={409: conflict("idempotency-conflict"), 413: {"model": ProblemDetails},
                        422: {"model": ProblemDetails}, 429: {"model": ProblemDetails},
                        507: {"model": ProblemDetails}},
             summary="Submit a job")
async def submit_job(spec: JobSpec, response: Response, runtime: RuntimeDep, caller: CallerDep,
                     idempotency_key: Annotated[str | None, Header(alias="Idempotency-Key", max_length=200,
                                                                   description="Retrying with the same key returns "
                                                                               "the same job (keys are per API key).")]
                     = None):
    """Validate a job (schema, caps, upload checks, scene and targets) and queue it. Answers ``202`` with
    the job id and a ``Location`` header; a bad job is a ``422`` naming the field."""
    service = runtime.service
    if idempotency_key:
        existing = await runtime.admission.run(caller.owner, service.find_idempotent, caller, idempotency_key)
        if existing is not None:
            return _accepted(response, existing.id, existing.status, await _fingerprint(spec),
                             existing.fingerprint)
    await validate_job(spec, runtime, caller.owner)
    if spec.warm_start is not None:  # the source: a job of this key with the same scene and keys
        try:
            await runtime.admission.run(caller.owner, lambda: source_checkpoint(runtime.service.states, spec,
                                                                                caller.owner, read=False))
        except InvalidJob as exc:
            raise ProblemError(422, "Invalid job", str(exc), slug="invalid-job",
                               errors=[(exc.field, exc.message)]) from None

    def submit():
        limits = runtime.settings.limits
        return service.submit(spec, caller, idempotency_key, max_active=limits.active_jobs_per_key, limits=limits)

    try:
        record, _ = await runtime.admission.run(caller.owner, submit)
    except TooManyJobs as exc:
        raise ProblemError(429, "Too many jobs", str(exc), slug="too-many-jobs", headers={"Retry-After": "30"}) from None
    except StorageQuota as exc:
        raise ProblemError(507, "Storage quota reached", str(exc), slug="storage-quota") from None
    return _accepted(response, record.id, record.status, await _fingerprint(spec), record.fingerprint)


async def _fingerprint(spec: JobSpec) -> str:
    """The job's hash, in a worker thread (it serializes the whole job: uploads included)."""
    return await anyio.to_thread.run_sync(spec.fingerprint)


def _accepted(response: Response, job_id: str, status: JobStatus, spec_fingerprint: str,
              fingerprint: str | None) -> JobAccepted:
    if fingerprint not in (None, spec_fingerprint):
        raise ProblemError(409, "Conflict", "this Idempotency-Key was used for a different job",
                           slug="idempotency-conflict")
    base = f"/v1/jobs/{job_id}"
    response.headers["Location"] = base
    return JobAccepted(id=job_id, status=status, links={"self": base, "events": f"{base}/events",
                                                        "iterations": f"{base}/iterations", "cancel": f"{base}/cancel"})


@router.get("", response_model=JobPage, summary="List jobs")
def list_jobs(runtime: RuntimeDep, settings: SettingsDep, caller: CallerDep,
              status: Annotated[JobStatus | None, Query(description="Only jobs with this status.")] = None,
              limit: Annotated[int, Query(ge=1, le=200, description="Page size.")] = 50,
              cursor: Annotated[str | None, Query(pattern="^[0-9a-f]{20}$", description="From a previous page.")] = None):
    """The caller's jobs (every job for an admin key), newest first, ``limit`` per page."""
    items: list[JobPublic] = []
    next_cursor = None
    for record in runtime.service.records(caller, status, before=cursor):
        if len(items) == limit:
            next_cursor = items[-1].id
            break
        items.append(job_public(record, runtime.service.states.files(record.id), settings))
    return JobPage(items=items, next_cursor=next_cursor)


@router.get("/{job_id}", response_model=JobPublic, responses={404: {"model": ProblemDetails}}, summary="A job")
def get_job(job_id: str, request: Request, runtime: RuntimeDep, settings: SettingsDep, caller: ReaderDep):
    """Status, current iteration, latest parameters and metrics, plan, error. ``read_token`` is a fresh
    read token only for a bearer key (a request with ``?token=`` gets none: tokens expire)."""
    record = runtime.service.record(job_id, caller)
    return job_public(record, runtime.service.states.files(job_id), settings, mint_token=may_mint_token(request))


@router.post("/{job_id}/cancel", status_code=202, response_model=JobPublic,
             responses={404: {"model": ProblemDetails}, 409: conflict("job-finished")}, summary="Cancel a job")
def cancel_job(job_id: str, runtime: RuntimeDep, settings: SettingsDep, caller: CallerDep):
    """A queued job is canceled at once; a running one stops at its next training step and keeps
    its artifacts. Canceling a finished job is a ``409``."""
    record = runtime.service.cancel(job_id, caller)
    return job_public(record, runtime.service.states.files(job_id), settings)


@router.post("/{job_id}/images", status_code=202, response_model=JobPublic,
             responses={404: {"model": ProblemDetails}, 409: conflict("job-not-running")},
             summary="Write images at the next iteration")
def request_images(job_id: str, runtime: RuntimeDep, settings: SettingsDep, caller: CallerDep):
    """The running job writes the renders of every view and the gradient images at its next
    iteration, whatever its images schedule (by default they take at most 5% of the run). A job
    that is not running is a ``409``."""
    record = runtime.service.request_images(job_id, caller)
    return job_public(record, runtime.service.states.files(job_id), settings)


@router.delete("/{job_id}", status_code=204, responses={404: {"model": ProblemDetails}, 409: conflict("job-active")},
               summary="Delete a job")
def delete_job(job_id: str, runtime: RuntimeDep, caller: CallerDep):
    """Delete a finished job and all its files (cancel an active one first: ``409``)."""
    runtime.service.delete(job_id, caller)
    return Response(status_code=204)

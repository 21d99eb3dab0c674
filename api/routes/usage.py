"""``/v1/usage``: the calling key's use of the service against its quotas (issue 38)."""

from __future__ import annotations

import anyio
from fastapi import APIRouter

from api.bodies import GuardedRoute
from api.deps import CallerDep, RuntimeDep
from api.problems import ProblemDetails
from schemas.usage import KeyUsage, Quota
from services.jobs.quotas import key_use

router = APIRouter(prefix="/v1/usage", tags=["usage"], route_class=GuardedRoute,
                   responses={401: {"model": ProblemDetails, "description": "Missing or wrong API key."}})


@router.get("", response_model=KeyUsage, summary="This key's use against its quotas")
async def usage(runtime: RuntimeDep, caller: CallerDep) -> KeyUsage:
    """Stored bytes, active and running jobs, admission work and unfinished experiments of the
    calling key, each with its quota and the setting that sets it."""
    limits, owner = runtime.settings.limits, caller.owner
    in_flight = runtime.admission.in_flight(owner)
    use = await runtime.admission.run(owner, key_use, runtime.service.states, owner)
    experiments = await runtime.admission.run(owner, runtime.experiments.open_count, owner)
    return KeyUsage(
        stored_bytes=Quota(used=use.stored_bytes, limit=limits.key_bytes, setting="NDRF_MAX_KEY_BYTES"),
        active_jobs=Quota(used=use.active_jobs, limit=limits.active_jobs_per_key,
                          setting="NDRF_MAX_ACTIVE_JOBS_PER_KEY"),
        running_jobs=Quota(used=await anyio.to_thread.run_sync(runtime.queue.running, owner),
                           limit=limits.running_jobs_per_key, setting="NDRF_MAX_RUNNING_JOBS_PER_KEY"),
        admission=Quota(used=in_flight, limit=runtime.settings.admission_per_key,
                        setting="NDRF_ADMISSION_PER_KEY"),
        experiments=Quota(used=experiments, limit=limits.experiments_per_key, setting="NDRF_MAX_EXPERIMENTS_PER_KEY"),
        job_bytes=limits.job_bytes, child_memory_bytes=limits.child_memory_bytes)

"""A key's use of the service against its quotas (``GET /v1/usage``)."""

from __future__ import annotations

from pydantic import BaseModel, Field


class Quota(BaseModel):
    used: int = Field(description="What the key uses now.")
    limit: int = Field(description="Its quota (the setting named in 'setting'); 0: no cap.")
    setting: str = Field(description="The environment variable that sets the quota.")


class KeyUsage(BaseModel):
    """The calling key's use against its quotas; an admin key sees its own."""

    stored_bytes: Quota = Field(description="Bytes of the key's stored files (jobs, views).")
    active_jobs: Quota = Field(description="Queued or running jobs of the key.")
    running_jobs: Quota = Field(description="Jobs of the key that workers run now.")
    admission: Quota = Field(description="Scene checks, views and submissions of the key that this API process runs "
                                         "or holds in the key's line now.")
    experiments: Quota = Field(description="Unfinished experiments of the key.")
    job_bytes: int = Field(description="Disk budget of one job (NDRF_MAX_JOB_BYTES).")
    child_memory_bytes: int = Field(description="Memory of one sandboxed child: a scene check, a view or a job "
                                                "(NDRF_MAX_CHILD_MEMORY_BYTES); a key runs at most "
                                                "admission.limit scene checks and views at once per API process.")

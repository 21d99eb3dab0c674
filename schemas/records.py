"""What the API returns about jobs (the job record of the store, as the public sees it)."""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

JobStatus = Literal["queued", "running", "succeeded", "failed", "canceled"]
FINISHED: frozenset[str] = frozenset({"succeeded", "failed", "canceled"})


class JobPublic(BaseModel):
    """A job as clients see it."""

    id: str = Field(description="Job id (20 lowercase hex characters, time-ordered).")
    name: str | None = Field(None, description="The job's label.")
    status: JobStatus = Field(description="queued, running, succeeded, failed or canceled.")
    method: str = Field(description="Gradient method.")
    scene: str = Field(description="Scene label (built-in name or 'xml').")
    created: str = Field(description="Submission time (ISO 8601, UTC).")
    updated: str = Field(description="Last change of the record (ISO 8601, UTC).")
    iteration: int | None = Field(None, description="Last completed iteration (0-based), if any.")
    iterations: int = Field(description="Iterations requested.")
    attempts: int = Field(0, description="Attempts so far (a worker that dies leaves the job to another).")
    parameters: dict[str, float] | None = Field(None, description="Latest parameter values, by scalar label.")
    target: dict[str, float] | None = Field(None, description="Target values (synthetic targets only).")
    metrics: dict[str, Any] | None = Field(None, description="Latest iteration: loss, residual norms, seconds per "
                                                              "phase, sanitized sample counts.")
    plan: dict[str, Any] | None = Field(None, description="What the job simulates (fields, terms) and why.")
    error: str | None = Field(None, description="Why the job failed.")
    field: str | None = Field(None, description="The job-file field an error concerns.")
    elapsed_seconds: float | None = Field(None, description="Seconds since the job started running.")
    eta_seconds: float | None = Field(None, description="Estimated seconds to completion.")


class JobAccepted(BaseModel):
    id: str = Field(description="Job id.")
    status: JobStatus = Field(description="Status after submission (queued, or the status of the job an "
                                          "Idempotency-Key already named).")
    links: dict[str, str] = Field(description="Related resources.")


class JobPage(BaseModel):
    items: list[JobPublic] = Field(description="Jobs, newest first.")
    next_cursor: str | None = Field(None, description="Pass as ?cursor= for the next page; null at the end.")


class IterationRecord(BaseModel):
    """One iteration of the loop (Sec. 5)."""

    model_config = {"extra": "allow"}

    iteration: int = Field(description="0-based iteration index.")
    loss: float | None = Field(description="Image loss z(y), summed over sensors.")
    parameters: list[float] = Field(description="Parameters at which loss and gradient were evaluated.")
    updated_parameters: list[float] = Field(description="Parameters after the Adam step and projection.")
    dz_dp: list[float] = Field(description="Gradient of the loss w.r.t. every scalar (Eq. 10).")
    seconds: dict[str, float] = Field(description="Seconds per phase: training, rendering, gradient.")

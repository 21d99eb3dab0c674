"""Records of jobs: the job record the store keeps (owned by ``services.jobs.state``), the record
the loop writes per iteration, and what the API returns.

``JobRecord`` is the only description of a job's state; the store keeps it as ``record.json`` and
:class:`services.jobs.state.JobStates` is the only code that writes it.
"""

from __future__ import annotations

from enum import StrEnum
from typing import Any

from pydantic import BaseModel, ConfigDict, Field

from schemas.plan import Plan


class JobStatus(StrEnum):
    """``queued -> running -> succeeded | failed | canceled``; a running job whose worker stops
    goes back to ``queued`` (it resumes from its checkpoint)."""

    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"

    @property
    def finished(self) -> bool:
        return self in FINISHED


FINISHED: frozenset[JobStatus] = frozenset({JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELED})
ACTIVE: frozenset[JobStatus] = frozenset({JobStatus.QUEUED, JobStatus.RUNNING})


class JobRecord(BaseModel):
    """A job's state in the store. Written only through ``services.jobs.state.JobStates``."""

    model_config = ConfigDict(extra="ignore")

    id: str
    name: str | None = None
    owner: str = Field("anonymous", description="Id of the API key that created the job ('anonymous' without keys).")
    status: JobStatus
    method: str
    scene: str
    created: str
    updated: str
    started: str | None = None
    finished: str | None = None
    iteration: int | None = Field(None, description="Last completed iteration.")
    iterations: int
    attempts: int = Field(0, description="Attempts started so far.")
    attempt: str | None = Field(None, description="Id of the attempt that owns the job (the fence).")
    crashes: int = Field(0, description="Attempts that ended without reporting (their process died).")
    worker: str | None = None
    error: str | None = None
    field: str | None = None
    cancel_requested: bool = False
    images_requested: bool = Field(False, description="Someone asked for the renders and gradient images of the "
                                                      "next iteration (cleared when they are written).")
    idempotency_key: str | None = None
    fingerprint: str | None = None
    experiment: str | None = Field(None, description="Id of the experiment this job is a run of.")
    varied: dict[str, Any] | None = Field(None, description="The experiment's varied fields and their values.")


class IterationRecord(BaseModel):
    """One iteration of the loop (Sec. 5), as the loop writes it and the API returns it."""

    model_config = ConfigDict(extra="forbid")

    iteration: int = Field(description="0-based iteration index.")
    loss: float | None = Field(description="Image loss z(y), summed over sensors (of blurred images while a "
                                           "geometry job's loss is blurred: plan.json's recipe.blur).")
    parameters: list[float] = Field(description="Parameters at which loss and gradient were evaluated (the scalars "
                                                "plan.json lists: every parameter but textures).")
    updated_parameters: list[float] = Field(description="Parameters after the optimizer's step and projection.")
    dz_dp: list[float] = Field(description="Gradient of the loss w.r.t. every listed scalar (Eq. 10).")
    learning_rate: float = Field(description="Learning rate of this step (the job's schedule).")
    views: list[int] = Field(default_factory=list, description="The target views (sensor indices) of this "
                                                               "iteration's batch.")
    optimizer: dict[str, float] | None = Field(None, description="The optimizer's own state after the step "
                                                                 "(Levenberg-Marquardt: its trust radius).")
    seconds: dict[str, float] = Field(description="Seconds per phase: training (the fields), gradient (candidates, "
                                                  "losses, dz/dp and, for second-order steps, the Jacobian of the "
                                                  "batch), step (the optimizer), images (renders of every view and "
                                                  "gradient images, on iterations that write them).")
    sanitized: dict[str, int] = Field(default_factory=dict,
                                      description="Lanes or steps whose non-finite values were zeroed or skipped, "
                                                  "by where (cumulative over the run).")
    refused: dict[str, int] = Field(default_factory=dict,
                                    description="Steps refused and never written, by reason: a step that would move "
                                                "a shape to non-finite vertices or invert its triangles (cumulative "
                                                "over the run; the iteration's parameters are kept).")
    training_steps: int = Field(0, description="Training steps of the fields in this iteration.")
    residual_radiance: float | None = Field(None, description="Mean residual norm of the radiance field L_phi over "
                                                               "the iteration's steps.")
    residual_differential: float | None = Field(None, description="Mean residual norm of the differential field "
                                                                   "dL_theta.")
    parameter_error: float | None = Field(None, description="max |p - target| of the parameters the step was taken at, "
                                                            "over the scalars that are not a shape's (the listed "
                                                            "scalars and the textures' texels; synthetic targets "
                                                            "only; null when every parameter is a shape's: its "
                                                            "error is its Chamfer distance, in shapes).")
    estimate: list[float] | None = Field(None, description="The answer after this iteration: the best estimate of "
                                                           "every listed scalar from the iterations of its window "
                                                           "(services/solver/optimize/answer.py); what the run returns "
                                                           "if it ends here.")
    standard_error: list[float] | None = Field(None, description="The standard error of each scalar of estimate "
                                                                 "(null while the window is too short to give one).")
    estimate_window: list[int] | None = Field(None, description="[first, last] iteration the estimate averages.")
    estimate_error: float | None = Field(None, description="max |estimate - target|, over the scalars parameter_error "
                                                           "compares (synthetic targets only).")
    images: bool = Field(False, description="Whether renders and gradient images were written this iteration.")
    textures: dict[str, dict[str, Any]] | None = Field(
        None, description="Per texture parameter, by key (texture jobs only; their texels are not in parameters, "
                          "updated_parameters or dz_dp): shape, mean per channel, min, max of the parameters the "
                          "step was taken at, gradient_rms of dz/dp and, for synthetic targets, rmse and psnr (dB) "
                          "against the target texture.")
    shapes: dict[str, dict[str, Any]] | None = Field(
        None, description="Per optimized mesh, by shape id (shape jobs only; its vertices are not in parameters, "
                          "updated_parameters or dz_dp): vertices, faces and, with a synthetic target mesh, chamfer, "
                          "the symmetric Chamfer distance (scene units) of the surface the step was taken at to the "
                          "target surface, of any topology: the mean distance of points uniform by area on each to "
                          "the other surface, both ways, averaged.")
    preview_scales: list[float] | None = Field(None, description="Value of full red in each gradient preview.")


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
    estimate: dict[str, float] | None = Field(None, description="The answer so far, by scalar label: the estimate "
                                              "of the latest iteration (services/solver/optimize/answer.py), the "
                                              "initial values before the first.")
    standard_error: dict[str, float] | None = Field(None, description="The standard error of each scalar of "
                                                                      "estimate, by label (null while too few "
                                                                      "iterations were seen).")
    target_values: dict[str, float] | None = Field(None, description="Target values, by scalar label (synthetic "
                                                   "targets only).")
    parameters: dict[str, float] | None = Field(None, deprecated="the same as estimate; removed in /v2",
                                                description="Deprecated: the same as estimate.")
    target: dict[str, float] | None = Field(None, deprecated="the same as target_values; removed in /v2",
                                            description="Deprecated: the same as target_values.")
    metrics: dict[str, Any] | None = Field(None, description="Latest iteration: loss, residual norms, seconds per "
                                                              "phase, sanitized sample counts, the texture "
                                                              "summaries of a texture job.")
    plan: Plan | None = Field(None, description="What the job simulates and why (plan.json).")
    error: str | None = Field(None, description="Why the job failed.")
    field: str | None = Field(None, description="The job-file field an error concerns.")
    elapsed_seconds: float | None = Field(None, description="Seconds since the job started running.")
    eta_seconds: float | None = Field(None, description="Estimated seconds to completion.")
    experiment: str | None = Field(None, description="Id of the experiment this job is a run of.")
    varied: dict[str, Any] | None = Field(None, description="Values of the experiment's varied fields.")
    images_requested: bool = Field(False, description="The job writes every view's render and its gradient images "
                                                      "at its next iteration (POST /v1/jobs/{id}/images).")
    read_token: str | None = Field(None, description="Short-lived token for this job's GET routes (events, images, "
                                                     "downloads), for clients that cannot send headers: "
                                                     "?token=<it>. Null without API keys.")


class JobAccepted(BaseModel):
    id: str = Field(description="Job id.")
    status: JobStatus = Field(description="Status after submission (queued, or the status of the job an "
                                          "Idempotency-Key already named).")
    links: dict[str, str] = Field(description="Related resources.")


class JobPage(BaseModel):
    items: list[JobPublic] = Field(description="Jobs, newest first.")
    next_cursor: str | None = Field(None, description="Pass as ?cursor= for the next page; null at the end.")

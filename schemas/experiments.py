"""Experiments: a sweep over the fields of one job (``POST /v1/experiments``, ``ndrf experiment``).

An experiment names a ``base`` job and what to vary: ``grid`` (every combination of the listed
values), ``random`` (``samples`` seeded draws, the same draws for every grid combination) and
``seeds`` (each configuration runs once per seed). Every run is an ordinary job carrying the
experiment's id and its varied values. Field paths address any job field: ``method``,
``learning_rate``, ``training.steps_per_iteration``, ``render.resolution``, ``parameters[0].init``
or by key ``parameters[red.reflectance.value].init``, ``targets.synthetic.values[red.reflectance.value]``.

The stored record (:class:`ExperimentRecord`) is written only by
``services.experiments.state.ExperimentStates``; the rest are what the API returns.
"""

from __future__ import annotations

import math
from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, JsonValue, field_validator, model_validator

from schemas.job import JobSpec

FIELD_PATH_HELP = ("A job field path: 'method', 'learning_rate', 'training.steps_per_iteration', 'render.spp', "
                   "'parameters[0].init' (or 'parameters[<key>].init'), 'targets.synthetic.values[<key>]', ...")


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


class RandomRange(_Strict):
    """A number drawn uniformly from ``[min, max]`` (log-uniformly with ``log``)."""

    min: float = Field(description="Lower end of the range.")
    max: float = Field(description="Upper end of the range.")
    log: bool = Field(False, description="Draw log-uniformly (both ends must be positive).")
    integer: bool = Field(False, description="Round the draw to the nearest integer.")

    @model_validator(mode="after")
    def _ordered(self):
        if not self.min <= self.max:
            raise ValueError(f"min must not exceed max, got [{self.min}, {self.max}]")
        if self.log and self.min <= 0:
            raise ValueError("a log-uniform range needs min > 0")
        return self


class RandomChoice(_Strict):
    """One of ``values``, drawn uniformly."""

    values: list[JsonValue] = Field(min_length=1, max_length=1000, description="The values to draw from.")


class Objective(_Strict):
    """What "best run" means."""

    metric: Literal["parameter_error", "loss", "seconds", "time_to_error"] = Field(
        "parameter_error", description="parameter_error: final max |p - target| (synthetic targets); loss: final "
                                       "image loss; seconds: compute seconds of the run; time_to_error: seconds until "
                                       "the parameter error first fell to target_error.")
    goal: Literal["min", "max"] = Field("min", description="Minimise or maximise the metric.")


Values = list[JsonValue]


class Sweep(_Strict):
    """What varies (the part an append extends)."""

    grid: dict[str, Values] = Field(default_factory=dict, description="Field path -> values; every combination "
                                                                       "is run. " + FIELD_PATH_HELP)
    random: dict[str, RandomRange | RandomChoice] = Field(
        default_factory=dict, description="Field path -> {min, max, log, integer} or {values}; 'samples' seeded "
                                          "draws, each combined with every grid combination.")
    samples: int = Field(1, ge=1, le=1000, description="Random draws (with 'random'; 1 without).")
    seeds: list[int] | None = Field(None, min_length=1, max_length=1000,
                                    description="Each configuration runs once per seed (sets the job's 'seed'). "
                                                "Default: the base job's seed.")

    @field_validator("grid")
    @classmethod
    def _values(cls, grid):
        for path, values in grid.items():
            if not 1 <= len(values) <= 1000:
                raise ValueError(f"grid[{path}] needs 1 to 1000 values, got {len(values)}")
        return grid

    @field_validator("seeds")
    @classmethod
    def _seeds(cls, seeds):
        if seeds is not None:
            if len(set(seeds)) != len(seeds):
                raise ValueError(f"seeds must be unique, got {seeds}")
            if any(not 0 <= s <= 2**31 - 1 for s in seeds):
                raise ValueError("seeds must lie in [0, 2^31 - 1]")
        return seeds


class ExperimentWarmStart(_Strict):
    """Every run but the first warm-started from the first run (run 0): its job gets
    ``warm_start: {job: <run 0's job>, ...}`` once run 0 has succeeded."""

    source: Literal["first_run"] = Field("first_run", description="Where the fields come from: 'first_run', run 0 "
                                                                   "(the first grid combination, first seed), run "
                                                                   "cold before any other run starts.")
    parameters: bool = Field(False, description="Also start from run 0's final parameters (else each run's init).")
    top_up_steps: int | None = Field(None, ge=0, le=100000,
                                     description="Most training steps of each warm run's adaptive top-up (the job's "
                                                 "warm_start.top_up_steps). Default: a quarter of "
                                                 "training.warmup_steps.")


class ExperimentSpec(Sweep):
    """An experiment: the base job, what varies, how many runs at once, and the objective."""

    name: str | None = Field(None, max_length=200, description="Optional label.")
    base: JobSpec | None = Field(None, description="The job every run starts from (the job file).")
    base_job: str | None = Field(None, pattern="^[0-9a-f]{20}$",
                                 description="Instead of 'base': the id of an existing job whose file every run "
                                             "starts from ('sweep this job').")
    random_seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed of the random draws.")
    max_concurrent: int = Field(2, ge=1, le=64, description="Most runs queued or running at once, across all "
                                                             "workers.")
    objective: Objective = Field(default_factory=Objective, description="What the best run minimises or maximises.")
    target_error: float = Field(0.05, gt=0, le=1e6, description="The parameter error whose time to reach is reported "
                                                                 "per run (time_to_error).")
    warm_start: ExperimentWarmStart | None = Field(
        None, description="'first_run' (or {source, parameters, top_up_steps}): run 0 runs cold, and every other run "
                          "waits for it and starts from its trained fields (warm_start: {job: run 0's job}). If run "
                          "0 fails or is canceled, the other runs fail without a job (retry re-runs run 0 first). "
                          "Default: every run cold.")

    @field_validator("warm_start", mode="before")
    @classmethod
    def _warm_start_shorthand(cls, value):
        return {"source": value} if isinstance(value, str) else value

    @model_validator(mode="after")
    def _one_base(self):
        if (self.base is None) == (self.base_job is None):
            raise ValueError("give the base job either inline ('base') or by id ('base_job'), exactly one")
        return self


class ExperimentAppend(_Strict):
    """More runs for an existing experiment: more values of fields it already varies, more seeds,
    more random draws. Runs that exist already are kept (finished ones are not run again)."""

    grid: dict[str, Values] = Field(default_factory=dict, description="Values to add per already varied grid field.")
    seeds: list[int] = Field(default_factory=list, max_length=1000, description="Seeds to add.")
    samples: int = Field(0, ge=0, le=1000, description="Random draws to add.")


# ------------------------------------------------------------------------------------ records

class ExperimentStatus(StrEnum):
    QUEUED = "queued"          # no run started yet
    RUNNING = "running"        # runs pending, queued or running
    SUCCEEDED = "succeeded"    # every run succeeded
    FAILED = "failed"          # every run finished, some failed
    CANCELED = "canceled"      # canceled; nothing queued or running any more

    @property
    def finished(self) -> bool:
        return self in (ExperimentStatus.SUCCEEDED, ExperimentStatus.FAILED, ExperimentStatus.CANCELED)


RunStatus = Literal["pending", "admitting", "queued", "running", "succeeded", "failed", "canceled"]
RUN_ACTIVE = frozenset({"admitting", "queued", "running"})
RUN_FINISHED = frozenset({"succeeded", "failed", "canceled"})


class RunState(BaseModel):
    """One run of an experiment as its record keeps it. ``pending`` runs have no job yet: the
    scheduler creates it when a slot under ``max_concurrent`` is free."""

    model_config = ConfigDict(extra="ignore")

    index: int = Field(description="0-based run index (stable across appends).")
    key: str = Field(description="Canonical JSON of the run's values (its identity).")
    values: dict[str, Any] = Field(description="Field path -> value of every varied field, 'seed' included.")
    status: RunStatus = "pending"
    job: str | None = Field(None, description="Id of the run's current job.")
    jobs: list[str] = Field(default_factory=list, description="Every job of this run (retries add one).")
    admissions: int = Field(0, description="Times the run was admitted (its idempotency key counts them).")
    since: float | None = Field(None, description="When the current admission started (epoch seconds).")
    error: str | None = Field(None, description="Why the run failed without a job (its warm-start source failed).")


class ExperimentRecord(BaseModel):
    """An experiment in the store (``experiments/<id>/experiment.json``; the base job is beside
    it in ``base.json``)."""

    model_config = ConfigDict(extra="ignore")

    id: str
    name: str | None = None
    owner: str = "anonymous"
    status: ExperimentStatus = ExperimentStatus.QUEUED
    created: str
    updated: str
    finished: str | None = None
    canceled: bool = Field(False, description="Canceled by its owner (retry and append reopen it).")
    sweep: dict[str, Any] = Field(description="The experiment spec without its base (grid, random, seeds, ...).")
    base_method: str = Field("", description="The base job's method.")
    base_scene: str = Field("", description="The base job's scene label.")
    base_iterations: int | None = Field(None, description="The base job's iterations.")
    base_job: str | None = Field(None, description="The job the base was taken from, if any.")
    varied: list[str] = Field(description="The field paths whose values differ between runs.")
    runs: list[RunState] = Field(default_factory=list)


# ---------------------------------------------------------------------------------- API views

class RunRow(BaseModel):
    """One run as ``GET /v1/experiments/{id}/runs`` and ``results.csv`` give it."""

    index: int = Field(description="Run index.")
    job: str | None = Field(None, description="Job id (null while pending).")
    status: RunStatus = Field(description="pending (waiting for a slot), queued, running, succeeded, failed, canceled.")
    varied: dict[str, Any] = Field(description="Values of the varied fields.")
    seed: int | None = Field(None, description="The run's seed.")
    iterations: int = Field(0, description="Iterations completed.")
    iterations_planned: int | None = Field(None, description="Iterations requested.")
    final_loss: float | None = Field(None, description="Image loss of the last completed iteration.")
    final_parameter_error: float | None = Field(None, description="max |p - target| of the latest parameters "
                                                                  "(synthetic targets only).")
    seconds: float | None = Field(None, description="Compute seconds: the iterations' phases summed (warm-up "
                                                    "included).")
    wall_seconds: float | None = Field(None, description="Seconds from the job's start to its end (or now).")
    time_to_error: float | None = Field(None, description="Compute seconds until the parameter error first fell to "
                                                          "the experiment's target_error (null: not reached).")
    attempts: int = Field(0, description="Jobs this run has had (a retry adds one).")
    error: str | None = Field(None, description="Why the run's job failed (or why the run got no job).")
    warm_start: dict[str, Any] | None = Field(None, description="What the run reused (its job's plan.json "
                                                                "warm_start: source job, fields, top-up steps and "
                                                                "seconds, warm-up steps saved); null: a cold run.")


class Aggregate(BaseModel):
    """Mean and spread over seeds of one configuration (the varied values but the seed)."""

    configuration: dict[str, Any] = Field(description="Values of the varied fields other than the seed.")
    runs: int = Field(description="Runs of this configuration.")
    succeeded: int = Field(description="Of which succeeded.")
    metrics: dict[str, dict[str, float | None]] = Field(
        description="Per metric (final_loss, final_parameter_error, seconds, time_to_error): mean, std (sample "
                    "standard deviation), min, max and n over the succeeded runs.")


class BestRun(BaseModel):
    index: int = Field(description="Run index.")
    job: str | None = Field(None, description="Its job.")
    varied: dict[str, Any] = Field(description="Its values.")
    value: float = Field(description="Its objective value.")


class ExperimentPublic(BaseModel):
    id: str = Field(description="Experiment id ('e' and 20 hex characters, time-ordered).")
    name: str | None = Field(None, description="Label.")
    status: ExperimentStatus = Field(description="queued, running, succeeded, failed or canceled.")
    created: str = Field(description="Creation time (ISO 8601, UTC).")
    updated: str = Field(description="Last change.")
    finished: str | None = Field(None, description="When the last run finished.")
    runs: int = Field(description="Runs in total.")
    counts: dict[str, int] = Field(description="Runs by status.")
    max_concurrent: int = Field(description="Most runs queued or running at once.")
    varied: list[str] = Field(description="Field paths that vary between runs.")
    objective: Objective = Field(description="What 'best' means.")
    best: BestRun | None = Field(None, description="The best succeeded run by the objective so far.")
    sweep: dict[str, Any] = Field(description="grid, random, samples, seeds, random_seed, target_error.")
    base_method: str = Field(description="The base job's method.")
    base_scene: str = Field(description="The base job's scene label.")
    aggregates: list[Aggregate] | None = Field(None, description="Mean and spread over seeds per configuration.")
    read_token: str | None = Field(None, description="Short-lived token for this experiment's GET routes "
                                                     "(?token=); null without API keys.")


class ExperimentAccepted(BaseModel):
    id: str = Field(description="Experiment id.")
    status: ExperimentStatus = Field(description="Status after the request.")
    runs: int = Field(description="Runs in total.")
    added: list[int] = Field(default_factory=list, description="Indices of the runs this request added or re-queued.")
    links: dict[str, str] = Field(description="Related resources.")


class ExperimentPage(BaseModel):
    items: list[ExperimentPublic] = Field(description="Experiments, newest first.")
    next_cursor: str | None = Field(None, description="Pass as ?cursor= for the next page.")


class Curve(BaseModel):
    """Accuracy against time: one point per completed iteration."""

    label: str = Field(description="The run ('#3') or the configuration ('method=prb').")
    varied: dict[str, Any] = Field(description="Values of the varied fields (no seed for a configuration).")
    runs: list[int] = Field(description="Run indices behind the curve.")
    seconds: list[float] = Field(description="Compute seconds at the end of each iteration (mean over seeds).")
    parameter_error: list[float | None] = Field(description="max |p - target| after each iteration (mean).")
    parameter_error_spread: list[list[float]] | None = Field(None, description="[min, max] over seeds per point.")
    loss: list[float | None] = Field(description="Image loss of each iteration (mean).")
    initial_parameter_error: float | None = Field(None, description="max |p - target| at the initial parameters "
                                                                   "(the curve's value at 0 s).")


class Curves(BaseModel):
    runs: list[Curve] = Field(description="One curve per run with records.")
    configurations: list[Curve] = Field(description="Mean curve per configuration over its seeds (runs cut to the "
                                                     "shortest).")


def finite_or_none(value: Any) -> float | None:
    try:
        number = float(value)
    except (TypeError, ValueError):
        return None
    return number if math.isfinite(number) else None

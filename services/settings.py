"""The one ``Settings`` of the service (API, workers, CLI), read from the environment.

``REDIS_URL``   Redis of the queue and event streams; unset = the embedded default (jobs run
                in-process, same API)
``NDRF_STORE``  the artifact store (the source of truth): a folder, default ``./runs``, or
                ``s3://bucket/prefix`` (``NDRF_S3_ENDPOINT``; credentials from the AWS variables)
Everything else is ``NDRF_<FIELD>`` (for example ``NDRF_API_KEYS=key1,key2``); the caps on
untrusted input are ``NDRF_MAX_<FIELD>`` (:class:`Limits`).
"""

from __future__ import annotations

import hashlib
from functools import lru_cache
from typing import Annotated, Literal

from pydantic import AliasChoices, Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict


class Limits(BaseSettings):
    """Caps on untrusted input and on what one job may use; a request over a cap gets a 4xx
    naming the limit, a job that exceeds a budget while running fails naming it."""

    model_config = SettingsConfigDict(env_prefix="NDRF_MAX_", extra="ignore")

    resolution: int = Field(1024, ge=1, description="Largest film side in pixels (the job's or the scene's).")
    sensors: int = Field(64, ge=1, description="Most sensors in a scene.")
    spp: int = Field(4096, ge=1, description="Largest samples per pixel of any rendering in a job.")
    iterations: int = Field(2000, ge=1, description="Most iterations of one job.")
    parameters: int = Field(64, ge=1, description="Most optimized scalars (an RGB value counts 3) outside textures.")
    texels: int = Field(4 << 20, ge=1, description="Most texels of a job's texture parameters and vertices of its "
                                                   "optimized meshes, all together (an RGB texel and a vertex each "
                                                   "hold 3 scalars).")
    upload_bytes: int = Field(64 << 20, ge=1024, description="Largest request body.")
    body_memory_bytes: int = Field(64 << 20, ge=1 << 20, le=1 << 40,
                                   description="Most request-body bytes one API process holds at once, all requests "
                                               "together (at least upload_bytes); a body that would exceed it gets a "
                                               "503 with Retry-After. Bounds the API's memory whatever clients send: "
                                               "reading and parsing take about 2.5 times the bytes held.")
    mesh_bytes: int = Field(32 << 20, ge=1024, description="Largest single uploaded file (mesh, texture).")
    image_pixels: int = Field(4 << 20, ge=1, description="Largest target image (width x height), read from "
                                                          "its header before it is decoded.")
    image_values: int = Field(16 << 20, ge=1, description="Most decoded values of a target image (width x height "
                                                          "x channels), read from its header before it is "
                                                          "decoded: an EXR may declare hundreds of channels.")
    training_points: int = Field(65536, ge=64, description="Largest residual batch N x M per step.")
    training_steps: int = Field(200_000, ge=1, description="Most training steps of one job (warm-up + "
                                                           "iterations x steps per iteration).")
    field_parameters: int = Field(1 << 24, ge=1024, description="Most learned numbers in one neural field "
                                                                 "(hash tables and MLP weights).")
    job_seconds: float = Field(6 * 3600.0, ge=1.0, description="Wall-clock budget of one job attempt.")
    worker_samples_per_second: float = Field(
        5e5, ge=1.0, description="Samples a worker traces per second, for the estimate of a job's set-up and first "
                                 "iteration at submission (services.limits.check_first_iteration: its meshes, its "
                                 "synthetic targets, its renders and its fields' warm-up, in samples): a job "
                                 "estimated past half of NDRF_MAX_JOB_SECONDS is refused naming the field to change. "
                                 "The default is the slowest worker measured, 2 CPU cores shared with other work "
                                 "(5.4e5 to 1.2e6, python -m bench.first_iteration), rounded down; a "
                                 "deployment whose workers all have GPUs raises it (the API cannot know which "
                                 "worker takes the job).")
    job_bytes: int = Field(2 << 30, ge=1 << 20, description="Disk budget of one job's files in the store.")
    child_memory_bytes: int = Field(8 << 30, ge=256 << 20, description="Address-space limit of the sandboxed "
                                                                       "process that loads or runs a job.")
    view_seconds: float = Field(300.0, ge=1.0, description="Wall-clock limit of one view of a job's fields "
                                                        "(POST /v1/jobs/{id}/views), prb's comparison image included.")
    view_samples: int = Field(1 << 20, ge=4096, le=1 << 34,
                              description="Most samples of one view (POST /v1/jobs/{id}/views): width x height x "
                                          "spp, and the same for prb_spp. A view child's memory grows with them "
                                          "(the outside probe measured 7.2 GiB at 512 x 512 x 16); a view over "
                                          "it is refused with a 422 before any child starts. A view's sides "
                                          "and spp also stay within NDRF_MAX_RESOLUTION and NDRF_MAX_SPP.")
    preflight_seconds: float = Field(120.0, ge=1.0, description="Wall-clock limit of loading a scene at "
                                                                 "submission.")
    active_jobs_per_key: int = Field(32, ge=1, description="Most queued or running jobs of one API key.")
    running_jobs_per_key: int = Field(4, ge=0, le=10_000,
                                      description="Most running jobs of one API key at once, across every "
                                                  "worker: a free worker takes another key's job instead, or waits "
                                                  "(0: no cap). Within it, keys take turns (least recently served "
                                                  "first).")
    key_bytes: int = Field(20 << 30, ge=1 << 20, description="Most bytes of stored files of one API key (all its "
                                                             "jobs and views): a submission of a key at it is a "
                                                             "507, and a running job gets at most what is left "
                                                             "(NDRF_MAX_JOB_BYTES or less) and fails naming this "
                                                             "limit when it would pass it; nothing written is "
                                                             "lost.")
    streams_per_key: int = Field(64, ge=1, description="Most open event streams of one API key.")
    experiment_runs: int = Field(200, ge=1, description="Most runs of one experiment (grid x samples x seeds, "
                                                        "appends included).")
    experiments_per_key: int = Field(20, ge=1, le=10_000, description="Most unfinished experiments of one API key "
                                                                      "(a 429 beyond): each is refreshed by the "
                                                                      "scheduler while it runs.")
    experiment_checks: int = Field(4, ge=1, le=1000,
                                   description="Most sandboxed scene checks one experiment (or append) runs when "
                                               "it is created: one per distinct scene, parameters, targets and "
                                               "render settings, the first ones; the runs of the others are "
                                               "checked by the worker when they run, and fail there naming why.")
    # JSON bodies are checked by a scan of the raw bytes before they are parsed (api.bodies): the
    # work and memory of parsing and validating a body are bounded by these, not by its size.
    json_depth: int = Field(32, ge=4, le=1000, description="Deepest nesting of arrays and objects in a JSON body "
                                                           "(guards the parser's recursion and per-level work).")
    json_keys: int = Field(1000, ge=16, le=1_000_000, description="Most keys of one JSON object (guards against "
                                                                  "objects of millions of unknown keys, each one a "
                                                                  "validation error).")
    json_items: int = Field(10_000, ge=16, le=10_000_000, description="Most items of one JSON array (guards "
                                                                      "against lists of millions of values, each "
                                                                      "one parsed, validated and reported).")
    json_tokens: int = Field(50_000, ge=1000, le=100_000_000,
                             description="Most strings, containers and separators in one JSON body (bounds the "
                                         "objects a body can make the API build, whatever its size: uploads are "
                                         "few long base64 strings).")
    validation_errors: int = Field(20, ge=1, le=1000, description="Validation errors listed in a 422 response "
                                                                  "(the rest are counted, not listed): bounds the "
                                                                  "size of an error response.")


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="NDRF_", extra="ignore")

    redis_url: str | None = Field(None, validation_alias=AliasChoices("REDIS_URL", "NDRF_REDIS_URL"),
                                  description="Redis URL; unset runs jobs in-process (embedded).")
    store: str = Field("runs", validation_alias=AliasChoices("NDRF_STORE", "store"),
                       description="The artifact store: a folder path (one machine, or a shared volume), or "
                                   "s3://bucket/prefix (an S3-compatible bucket: several machines, no shared disk).")
    s3_endpoint: str = Field("", description="Endpoint URL of an S3-compatible server (http://host:port); empty: AWS "
                                             "S3 in AWS_REGION. Credentials come from AWS_ACCESS_KEY_ID and "
                                             "AWS_SECRET_ACCESS_KEY (or the other usual AWS variables).")
    s3_presign_bytes: int = Field(0, ge=0, description="Artifacts of at least this many bytes are served by a 307 "
                                                       "redirect to a pre-signed URL of the bucket instead of through "
                                                       "the API (0: never; the bucket must be reachable by clients).")
    s3_presign_seconds: int = Field(300, ge=10, le=7 * 86400, description="Lifetime of a pre-signed URL.")
    s3_public_endpoint: str = Field("", description="The S3 endpoint as clients reach it, for pre-signed URLs "
                                                    "(empty: s3_endpoint).")
    s3_usage_seconds: float = Field(300.0, ge=1.0, description="Seconds the store's total size (/metrics) is "
                                                               "reused before the bucket is listed again.")
    view_keep_seconds: float = Field(60.0, ge=0.0, le=3600.0,
                                     description="A job's warm view child (POST /v1/jobs/{id}/views: the checkpoint "
                                                 "restored once, then one view after another) is kept this long "
                                                 "after its last view; 0: every view starts its own child.")
    view_children: int = Field(2, ge=0, le=64, description="Most warm view children of one API process (the least "
                                                           "recently used one is closed first).")
    scratch: str = Field("", description="Local folder where workers stage scenes for their sandboxed "
                                         "processes (default: <tmp>/ndrf-scratch).")
    api_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Accepted bearer keys (comma-separated); each key sees only its own "
                                          "jobs. Empty: no authentication (loopback only, see allow_anonymous).")
    admin_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Keys that see and manage every job (comma-separated).")
    allow_anonymous: bool = Field(False, description="Allow `ndrf serve --host` on a non-loopback address "
                                                     "without API keys.")
    token_secret: str = Field("", description="Secret of the short-lived read tokens (default: derived from "
                                              "the API keys, so every API process agrees).")
    token_seconds: int = Field(3600, ge=10, le=7 * 86400, description="Lifetime of a read token.")
    metrics_public: bool = Field(False, description="Serve /metrics without a key. Off by default: with API keys "
                                                    "set, /metrics needs an admin key (it shows every tenant's "
                                                    "job counts, the store size and the queue depth).")
    body_read_seconds: float = Field(60.0, ge=1.0, le=3600.0,
                                     description="Time allowed to receive a request's whole body once its headers "
                                                 "are in (a 408 after): guards against slow bodies holding a "
                                                 "connection. uvicorn has no timeout on reading headers.")
    header_read_seconds: float = Field(10.0, ge=1.0, le=600.0,
                                       description="Time allowed to receive a request's line and headers, from "
                                                   "the connection's opening or the previous response: the "
                                                   "connection is closed after (guards against clients that hold "
                                                   "connections by sending headers slowly).")
    keep_alive_seconds: float = Field(5.0, ge=1.0, le=300.0, description="An idle keep-alive connection is closed "
                                                                         "after this long (uvicorn "
                                                                         "timeout_keep_alive).")
    max_connections: int = Field(1000, ge=1, le=100_000,
                                 description="Most concurrent connections and requests of one API process; beyond "
                                             "it new requests get a 503 (uvicorn limit_concurrency).")
    max_header_bytes: int = Field(16 << 10, ge=4096, le=16 << 20,
                                  description="Largest request line and headers (uvicorn's h11 "
                                              "h11_max_incomplete_event_size): a larger header section is a 400.")
    retention_days: float | None = Field(None, gt=0, description="Delete finished jobs older than this many "
                                                                 "days (unset: keep everything).")
    lease_seconds: float = Field(30.0, ge=1.0, le=600.0,
                                 description="A job whose worker stops renewing its lease for this long is "
                                             "taken over by another worker (renewal every lease/3).")
    max_attempts: int = Field(3, ge=1, le=100, description="Attempts before a job that keeps crashing its "
                                                          "worker is failed.")
    embedded_workers: int = Field(1, ge=1, le=16, description="Worker threads of the embedded mode.")
    preflight_workers: int = Field(2, ge=1, le=64, description="Scene loads, views and other blocking admission "
                                                               "work running at once in one API process, all "
                                                               "keys together.")
    admission_per_key: int = Field(1, ge=1, le=64, description="Of those, the most one key runs at once (its "
                                                               "further work waits in a line of its own, not in "
                                                               "the shared one): keep it below "
                                                               "preflight_workers, so that a key with nothing in "
                                                               "flight never waits behind another key's scene "
                                                               "checks or views.")
    redis_connections: int = Field(32, ge=2, le=1024, description="Redis connections of one API process for short "
                                                                  "commands (stream slots, event reads); a stream "
                                                                  "that finds none free within a second is refused "
                                                                  "with 503. Stream waits use one connection of "
                                                                  "their own, whatever the number of streams.")
    sandbox: Literal["auto", "required", "off"] = Field(
        "auto", description="Namespaces of the sandboxed children (no network, read-only filesystem but their work "
                            "folder, the store hidden, no capabilities): auto uses them where the machine allows "
                            "and logs an ERROR where it does not; required refuses to start a child without them; "
                            "off never uses them (docs/security.md).")
    sandbox_hide: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="More folders covered by an empty read-only tmpfs in sandboxed children "
                                          "(comma-separated): credentials or data the service's uid can read and "
                                          "a child must not (the store folder and the scratch folders always are).")
    device: Literal["auto", "cpu", "cuda"] = Field(
        "auto", description="Where jobs, views and scene checks run (NDRF_DEVICE, passed to every child): cpu "
                            "(Mitsuba's llvm_ad_rgb, torch on the CPU), cuda (cuda_ad_rgb and torch on the first "
                            "visible GPU; a child refuses to start where either cannot run), or auto (cuda where "
                            "both run, else cpu, with the reason logged). One GPU per worker: CUDA_VISIBLE_DEVICES "
                            "(docs/guide/deployment.md).")
    limits: Limits = Field(default_factory=Limits)

    @field_validator("device", mode="before")
    @classmethod
    def _device(cls, value):
        return value.strip().lower() or "auto" if isinstance(value, str) else value

    @field_validator("api_keys", "admin_keys", "sandbox_hide", mode="before")
    @classmethod
    def _split(cls, value):
        if isinstance(value, str):
            return [k.strip() for k in value.split(",") if k.strip()]
        return value

    @property
    def auth(self) -> bool:
        return bool(self.api_keys or self.admin_keys)

    def signing_secret(self) -> bytes:
        if self.token_secret:
            return self.token_secret.encode()
        material = "\n".join(sorted(self.api_keys + self.admin_keys))
        return hashlib.sha256(b"ndrf-read-token\n" + material.encode()).digest()


def key_id(key: str) -> str:
    """The id a job records as its owner: a hash of the key (the key itself is never stored)."""
    return hashlib.sha256(key.encode()).hexdigest()[:16]


@lru_cache
def get_settings() -> Settings:
    return Settings()

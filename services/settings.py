"""The one ``Settings`` of the service (API, workers, CLI), read from the environment.

``REDIS_URL``   Redis of the queue and event streams; unset = the embedded default (jobs run
                in-process, same API)
``NDRF_STORE``  root folder of the artifact store (the source of truth), default ``./runs``
Everything else is ``NDRF_<FIELD>`` (for example ``NDRF_API_KEYS=key1,key2``).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

from pydantic import AliasChoices, Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict
from typing_extensions import Annotated


class Limits(BaseSettings):
    """Caps on untrusted input; a request over a cap gets a 4xx naming the limit."""

    model_config = SettingsConfigDict(env_prefix="NDRF_MAX_", extra="ignore")

    resolution: int = Field(1024, ge=1, description="Largest film side in pixels.")
    spp: int = Field(4096, ge=1, description="Largest samples per pixel of any rendering in a job.")
    iterations: int = Field(2000, ge=1, description="Most iterations of one job.")
    parameters: int = Field(64, ge=1, description="Most optimized scalars (an RGB value counts 3).")
    upload_bytes: int = Field(64 << 20, ge=1024, description="Largest request body.")
    mesh_bytes: int = Field(32 << 20, ge=1024, description="Largest single uploaded file (mesh, texture).")
    image_pixels: int = Field(4 << 20, ge=1, description="Largest target image (width x height).")
    training_points: int = Field(65536, ge=64, description="Largest residual batch N x M per step.")


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="NDRF_", extra="ignore")

    redis_url: str | None = Field(None, validation_alias=AliasChoices("REDIS_URL", "NDRF_REDIS_URL"),
                                  description="Redis URL; unset runs jobs in-process (embedded).")
    store: Path = Field(Path("runs"), validation_alias=AliasChoices("NDRF_STORE", "store"),
                        description="Root folder of the artifact store.")
    api_keys: Annotated[list[str], NoDecode] = Field(
        default_factory=list, description="Accepted bearer keys (comma-separated); empty disables auth.")
    lease_seconds: float = Field(30.0, ge=1.0, le=600.0,
                                 description="A job whose worker stops renewing its lease for this long is "
                                             "taken over by another worker (renewal every lease/3).")
    max_attempts: int = Field(3, ge=1, le=100, description="Attempts before a job that keeps crashing its "
                                                          "worker is failed.")
    embedded_workers: int = Field(1, ge=1, le=16, description="Worker threads of the embedded mode.")
    limits: Limits = Field(default_factory=Limits)

    @field_validator("api_keys", mode="before")
    @classmethod
    def _split(cls, value):
        if isinstance(value, str):
            return [k.strip() for k in value.split(",") if k.strip()]
        return value


@lru_cache
def get_settings() -> Settings:
    return Settings()

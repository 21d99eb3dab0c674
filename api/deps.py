"""Dependencies of the routes (the FastAPI ``Annotated`` aliases used in signatures)."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request

from api.problems import ProblemError
from services.runtime import Runtime
from services.settings import Settings


def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


def get_settings(request: Request) -> Settings:
    return request.app.state.runtime.settings


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
SettingsDep = Annotated[Settings, Depends(get_settings)]


def require_api_key(request: Request, settings: SettingsDep) -> None:
    """With API keys configured, every /v1 route needs ``Authorization: Bearer <key>``. The query
    parameter ``access_token`` is accepted too, for EventSource and <img> (which cannot set headers)."""
    if not settings.api_keys:
        return
    header = request.headers.get("authorization", "")
    token = header[7:].strip() if header.lower().startswith("bearer ") else request.query_params.get("access_token", "")
    if not any(hmac.compare_digest(token.encode(), key.encode()) for key in settings.api_keys):
        raise ProblemError(401, "Unauthorized", "a valid API key is required: Authorization: Bearer <key>",
                           slug="unauthorized", headers={"WWW-Authenticate": 'Bearer realm="ndrf"'})


Authenticated = Depends(require_api_key)

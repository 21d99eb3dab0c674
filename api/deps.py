"""Dependencies of the routes (the FastAPI ``Annotated`` aliases used in signatures).

Authentication: with API keys configured, every ``/v1`` route needs ``Authorization: Bearer
<key>``; the caller is the key's owner id (:func:`services.settings.key_id`), or an admin. The GET
routes of one job also accept ``?token=`` with a read token of that job (:mod:`api.tokens`).
Without keys the service is single-tenant and anonymous (loopback only, unless
``NDRF_ALLOW_ANONYMOUS``).
"""

from __future__ import annotations

import hmac
from typing import Annotated
from urllib.parse import unquote_plus

from fastapi import Depends, Request

from api import tokens
from api.problems import ProblemError
from services.jobs.service import ANONYMOUS, Caller
from services.runtime import Runtime
from services.settings import Settings, key_id


def get_runtime(request: Request) -> Runtime:
    return request.app.state.runtime


def get_settings(request: Request) -> Settings:
    return request.app.state.runtime.settings


RuntimeDep = Annotated[Runtime, Depends(get_runtime)]
SettingsDep = Annotated[Settings, Depends(get_settings)]


def _unauthorized() -> ProblemError:
    return ProblemError(401, "Unauthorized", "a valid API key is required: Authorization: Bearer <key>",
                        slug="unauthorized", headers={"WWW-Authenticate": 'Bearer realm="ndrf"'})


def _bearer(request: Request) -> str | None:
    header = request.headers.get("authorization", "")
    return header[7:].strip() if header.lower().startswith("bearer ") else None


def _match(token: str, keys: list[str]) -> bool:
    return any(hmac.compare_digest(token.encode(), key.encode()) for key in keys)


def caller_of(request: Request, settings: Settings) -> Caller | None:
    """The caller a request's bearer key names (None: no valid key)."""
    return caller_for_key(_bearer(request), settings)


def caller_for_key(token: str | None, settings: Settings) -> Caller | None:
    """The caller a bearer key names (None: no valid key); anonymous without keys configured."""
    if not settings.auth:
        return Caller(ANONYMOUS, admin=True)
    if token is None:
        return None
    if _match(token, settings.admin_keys):
        return Caller(key_id(token), admin=True)
    if _match(token, settings.api_keys):
        return Caller(key_id(token))
    return None


def require_caller(request: Request, settings: SettingsDep) -> Caller:
    caller = caller_of(request, settings)
    if caller is None:
        raise _unauthorized()
    return caller


def literal_token(request: Request) -> str | None:
    """The ``token`` query parameter, its name spelled literally (the last one, as
    ``query_params.get``). A name that only decodes to ``token`` (``?tok%65n=...``) is not
    accepted: a log or a proxy that matches the literal name would not know it carries a secret."""
    token = None
    for part in request.url.query.split("&"):
        name, equals, value = part.partition("=")
        if name == "token" and equals:
            token = unquote_plus(value)
    return token


def reader_of(request: Request, settings: Settings, resource_id: str) -> Caller:
    """A bearer key, or (GET only) a read token of this very resource (a job or an experiment):
    the caller then reads that one resource, and the routes it opens only touch ``resource_id``."""
    caller = caller_of(request, settings)
    if caller is not None:
        return caller
    token = literal_token(request)
    if request.method == "GET" and token and tokens.verify(settings.signing_secret(), token, resource_id):
        request.state.read_token = True   # answers never mint a new token for it (tokens must expire)
        return Caller(f"token:{resource_id}", admin=True)
    raise _unauthorized()


def may_mint_token(request: Request) -> bool:
    """Whether an answer to ``request`` may carry a fresh read token: not when the request itself was
    authenticated by a read token (a token that renews itself never expires)."""
    return not getattr(request.state, "read_token", False)


def require_reader(request: Request, settings: SettingsDep, job_id: str) -> Caller:
    """A bearer key, or (GET only) a read token of this very job."""
    return reader_of(request, settings, job_id)


def require_admin(request: Request, settings: SettingsDep) -> Caller:
    caller = require_caller(request, settings)
    if not caller.admin:
        raise ProblemError(403, "Forbidden", "this route needs an admin key (NDRF_ADMIN_KEYS)", slug="forbidden")
    return caller


CallerDep = Annotated[Caller, Depends(require_caller)]
ReaderDep = Annotated[Caller, Depends(require_reader)]

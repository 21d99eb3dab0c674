"""The API's outer ASGI middleware: what is decided before a route runs.

- **Authentication from the headers.** With API keys set, a ``/v1`` request that may carry a body
  (any method but GET, HEAD and OPTIONS) without a valid bearer key gets its 401 at once: its body
  is never read, parsed or validated. (The routes check the key again; read tokens only open GET
  routes.)
- **The body cap** (``NDRF_MAX_UPLOAD_BYTES``): a declared ``Content-Length`` over it is a 413 before
  anything is read; a chunked body is counted as it arrives and stopped with a 413 at the cap.
- **The body memory** (``NDRF_MAX_BODY_MEMORY_BYTES``): the body bytes all requests of this process
  hold at once, counted as they arrive and held until the request is answered; a body that would
  go over (by its declared length, or as it arrives) is a 503 with ``Retry-After``, so concurrent
  large bodies cannot add up.
- **The body read time** (``NDRF_BODY_READ_SECONDS``): a body still incomplete that long after the
  headers is a 408. (uvicorn has no header read timeout: see docs/security.md.)
- **Security headers** on every response: ``X-Content-Type-Options: nosniff``,
  ``X-Frame-Options: DENY``, ``Referrer-Policy: no-referrer`` and a Content-Security-Policy (the
  dashboard's own scripts and styles only; nothing at all for API documents).
"""

from __future__ import annotations

import json
import time

import anyio
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from services.settings import Settings

#: Methods whose requests may carry a body.
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
DASHBOARD_CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: "
                 "blob:; connect-src 'self'; object-src 'none'; base-uri 'none'; form-action 'self'; "
                 "frame-ancestors 'none'")
API_CSP = "default-src 'none'; frame-ancestors 'none'; sandbox"
#: FastAPI's interactive docs load Swagger UI / ReDoc from a CDN with an inline script.
DOCS_PATHS = ("/docs", "/redoc")


class BodyTooLarge(Exception):
    """The body crossed the cap while it was being received."""


class BodyBusy(Exception):
    """The bodies being received by this process already hold ``NDRF_MAX_BODY_MEMORY_BYTES``."""


class BodyTimeout(Exception):
    """The body was not complete within ``NDRF_BODY_READ_SECONDS`` of the headers."""


def security_headers(path: str) -> list[tuple[bytes, bytes]]:
    headers = [(b"x-content-type-options", b"nosniff"), (b"x-frame-options", b"DENY"),
               (b"referrer-policy", b"no-referrer")]
    if path.startswith(DOCS_PATHS):
        return headers
    csp = API_CSP if path.startswith("/v1/") or path in ("/metrics", "/healthz", "/openapi.json") else DASHBOARD_CSP
    return headers + [(b"content-security-policy", csp.encode())]


class Guard:
    """See the module's docstring. ``settings`` are the app's."""

    def __init__(self, app: ASGIApp, settings: Settings):
        self.app, self.settings = app, settings
        self.limit = settings.limits.upload_bytes
        self.budget = max(settings.limits.body_memory_bytes, self.limit)
        self.held = 0   # body bytes reserved by the requests in progress (one event loop: no lock)

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        path: str = scope.get("path", "")
        extra = security_headers(path)
        started = False

        async def send_with_headers(message: Message) -> None:
            nonlocal started
            if message["type"] == "http.response.start":
                started = True
                present = {name.lower() for name, _ in message.get("headers", [])}
                message = {**message, "headers": [*message.get("headers", []),
                                                  *(h for h in extra if h[0] not in present)]}
            await send(message)

        headers = dict(scope.get("headers") or [])
        if self.settings.auth and path.startswith("/v1/") and scope.get("method") not in SAFE_METHODS \
                and not self._authenticated(headers.get(b"authorization", b"")):
            return await _problem(send_with_headers, scope, 401, "Unauthorized",
                                  "a valid API key is required: Authorization: Bearer <key>", "unauthorized",
                                  [(b"www-authenticate", b'Bearer realm="ndrf"'), (b"connection", b"close")])
        declared = headers.get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            return await _problem(send_with_headers, scope, 413, "Payload too large", self._too_large(),
                                  "too-large", [(b"connection", b"close")])
        if declared is not None and declared.isdigit() and self.held + int(declared) > self.budget:
            return await _problem(send_with_headers, scope, 503, "Busy", self._busy(), "busy",
                                  [(b"retry-after", b"5"), (b"connection", b"close")])
        seen = reserved = 0
        deadline = time.monotonic() + self.settings.body_read_seconds
        complete = False

        async def counted() -> Message:
            nonlocal seen, complete, reserved
            if complete:
                return await receive()
            try:
                with anyio.fail_after(max(0.0, deadline - time.monotonic())):
                    message = await receive()
            except TimeoutError:
                raise BodyTimeout(f"the request body was not received within {self.settings.body_read_seconds:g} "
                                  f"s (NDRF_BODY_READ_SECONDS)") from None
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                complete = not message.get("more_body", False)
                if seen > self.limit:
                    raise BodyTooLarge(self._too_large())
                if seen > reserved:   # held as it arrives: a slow client holds only what it sent
                    if self.held + seen - reserved > self.budget:
                        raise BodyBusy(self._busy())
                    self.held += seen - reserved
                    reserved = seen
            return message

        try:
            await self.app(scope, counted, send_with_headers)
        except BodyTooLarge:   # read outside a guarded route: answered here if nothing was sent yet
            if not started:
                await _problem(send_with_headers, scope, 413, "Payload too large", self._too_large(), "too-large",
                               [(b"connection", b"close")])
        except BodyBusy:
            if not started:
                await _problem(send_with_headers, scope, 503, "Busy", self._busy(), "busy",
                               [(b"retry-after", b"5"), (b"connection", b"close")])
        except BodyTimeout as exc:
            if not started:
                await _problem(send_with_headers, scope, 408, "Request timeout", str(exc), "body-timeout",
                               [(b"connection", b"close")])
        finally:
            self.held -= reserved

    def _busy(self) -> str:
        return (f"the API is receiving {self.budget} bytes of request bodies already (NDRF_MAX_BODY_MEMORY_BYTES); "
                f"retry later")

    def _too_large(self) -> str:
        return f"the request body exceeds the limit of {self.limit} bytes (NDRF_MAX_UPLOAD_BYTES)"

    def _authenticated(self, header: bytes) -> bool:
        from api.deps import caller_for_key

        text = header.decode("latin-1")
        key = text[7:].strip() if text.lower().startswith("bearer ") else None
        return caller_for_key(key, self.settings) is not None


async def _problem(send: Send, scope: Scope, status: int, title: str, detail: str, slug: str,
                   headers: list[tuple[bytes, bytes]]) -> None:
    body = json.dumps({"type": f"/problems/{slug}", "title": title, "status": status, "detail": detail,
                       "instance": scope.get("path")}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/problem+json"),
                            (b"content-length", str(len(body)).encode()), *headers]})
    await send({"type": "http.response.body", "body": body})

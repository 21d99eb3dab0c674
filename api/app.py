"""The FastAPI application: ``create_app(settings)``.

With ``REDIS_URL`` the API only queues jobs (workers run them); without it, the same API runs
jobs on worker threads of its own (the embedded default), each job in a sandboxed child process.
In embedded mode the in-process queue starts empty, so every unfinished job of the store is
re-enqueued at start-up; in Redis mode the API takes its turn of the locked reconciler (which
re-enqueues only jobs missing from the queue, and without a live attempt, for two lease
periods). The API process never imports Mitsuba or torch (an import-linter contract checks it).
"""

from __future__ import annotations

import logging
from contextlib import asynccontextmanager
from importlib.metadata import version

from fastapi import FastAPI
from starlette.types import ASGIApp, Receive, Scope, Send

from api import problems
from api.routes import artifacts, events, experiments, health, jobs, scenes
from api.routes.health import Snapshot
from api.streams import StreamHub
from services.runtime import build_runtime
from services.settings import Settings, get_settings

log = logging.getLogger(__name__)


class BodyLimit:
    """Refuse request bodies over ``limit`` bytes with a 413 problem, without reading them whole."""

    def __init__(self, app: ASGIApp, limit: int):
        self.app, self.limit = app, limit

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        declared = dict(scope.get("headers") or []).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > self.limit:
            return await self._refuse(scope, send)
        seen = 0

        async def counted():
            nonlocal seen
            message = await receive()
            if message["type"] == "http.request":
                seen += len(message.get("body", b""))
                if seen > self.limit:
                    raise _TooLarge()
            return message

        try:
            await self.app(scope, counted, send)
        except _TooLarge:
            await self._refuse(scope, send)

    async def _refuse(self, scope: Scope, send: Send) -> None:
        import json

        body = json.dumps({"type": "/problems/too-large", "title": "Payload too large", "status": 413,
                           "detail": f"the request body exceeds the limit of {self.limit} bytes (NDRF_MAX_UPLOAD_BYTES)",
                           "instance": scope.get("path")}).encode()
        await send({"type": "http.response.start", "status": 413,
                    "headers": [(b"content-type", b"application/problem+json"),
                                (b"content-length", str(len(body)).encode())]})
        await send({"type": "http.response.body", "body": body})


class _TooLarge(Exception):
    pass


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        import anyio

        from worker.main import make_worker

        runtime = build_runtime(settings)
        runtime.blocking = anyio.CapacityLimiter(settings.preflight_workers)
        app.state.runtime = runtime
        app.state.snapshot = Snapshot(runtime)
        if runtime.embedded:
            missing = await anyio.to_thread.run_sync(runtime.service.reconcile, 0.0)
            if missing:
                log.warning("re-enqueued %d unfinished job(s) at start-up", len(missing))
            runtime.start_embedded_workers(make_worker)
        else:
            await anyio.to_thread.run_sync(runtime.reconcile_periodically)
        app.state.streams = StreamHub(runtime)
        runtime.start_experiment_scheduler()
        try:
            yield
        finally:
            await app.state.streams.close()
            await runtime.events.aclose()
            await anyio.to_thread.run_sync(runtime.stop)

    app = FastAPI(
        title="NDRF inverse rendering",
        version=version("ndrf"),  # pyproject.toml's, as installed
        summary="Recover scene parameters from photographs with Neural Differential Radiance Fields.",
        lifespan=lifespan,
    )
    problems.install(app)
    for module in (jobs, artifacts, events, experiments, scenes, health):
        app.include_router(module.router)
    from api.dashboard import mount

    mount(app)
    app.add_middleware(BodyLimit, limit=settings.limits.upload_bytes)
    return app

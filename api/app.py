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

from api import accesslog, problems
from api.admission import Admission
from api.guard import Guard
from api.routes import artifacts, events, experiments, field_views, health, jobs, scenes, usage
from api.routes.health import Snapshot
from api.streams import StreamHub
from services.jobs.device import DeviceReport
from services.runtime import build_runtime
from services.settings import Settings, get_settings

log = logging.getLogger(__name__)


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or get_settings()

    @asynccontextmanager
    async def lifespan(app: FastAPI):
        import anyio

        from worker.main import make_worker

        runtime = build_runtime(settings)
        runtime.blocking = anyio.CapacityLimiter(settings.preflight_workers)
        runtime.admission = Admission(runtime.blocking, settings.admission_per_key)
        app.state.runtime = runtime
        app.state.snapshot = Snapshot(runtime)
        app.state.device = DeviceReport()
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
        redirect_slashes=False,   # a redirect would echo the request's Host header (issue 27)
    )
    accesslog.install()
    problems.install(app)
    for module in (jobs, artifacts, field_views, events, experiments, scenes, usage, health):
        app.include_router(module.router)
    from api.dashboard import mount

    mount(app)
    app.add_middleware(Guard, settings=settings)
    return app

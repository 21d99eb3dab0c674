"""``ndrf serve`` and ``ndrf worker``: the service's two processes (both read REDIS_URL and NDRF_STORE)."""

from __future__ import annotations

import ipaddress
import logging

import click

log = logging.getLogger(__name__)


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@click.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to bind.")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(1, 65535), help="Port.")
@click.option("--workers", "processes", default=1, show_default=True, type=click.IntRange(1, 64),
              help="API processes sharing the port (Redis mode only: the embedded queue lives in one process).")
def serve_command(host: str, port: int, processes: int) -> None:
    """Run the HTTP API and the dashboard. Without REDIS_URL, jobs run in this process's workers.

    Secure by default: on a non-loopback address it refuses to start without API keys
    (NDRF_API_KEYS), unless NDRF_ALLOW_ANONYMOUS=1 says anonymous access is intended."""
    import uvicorn

    from api.app import create_app
    from services.settings import get_settings

    settings = get_settings()
    if not is_loopback(host) and not settings.auth and not settings.allow_anonymous:
        raise click.ClickException(f"refusing to serve {host} without API keys: set NDRF_API_KEYS (and "
                                   f"NDRF_ADMIN_KEYS), or NDRF_ALLOW_ANONYMOUS=1 if anyone who reaches {host} "
                                   f"may run jobs and read every job")
    click.echo(f"ndrf serve on http://{host}:{port} (store {settings.store}, "
               f"{'redis ' + settings.redis_url if settings.redis_url else 'embedded workers'}, "
               f"{'API keys' if settings.auth else 'anonymous'})", err=True)
    if processes > 1:
        if not settings.redis_url:
            raise click.ClickException("--workers > 1 needs REDIS_URL: embedded mode keeps its queue in one process")
        # Each process builds its app from the environment (the store and Redis are shared state).
        uvicorn.run("api.app:create_app", factory=True, workers=processes, host=host, port=port,
                    **server_options(settings))
        return
    uvicorn.run(create_app(settings), host=host, port=port, **server_options(settings))


def server_options(settings) -> dict:
    """uvicorn's limits for slow or greedy clients (docs/security.md): idle keep-alive connections
    closed after ``NDRF_KEEP_ALIVE_SECONDS``, at most ``NDRF_MAX_CONNECTIONS`` connections and
    requests at once per process (a 503 beyond), headers of at most ``NDRF_MAX_HEADER_BYTES`` read
    within ``NDRF_HEADER_READ_SECONDS`` (:mod:`api.server`: h11, the implementation that enforces
    the header size, with a header timeout uvicorn lacks); the body's read time is the app's
    (``NDRF_BODY_READ_SECONDS``)."""
    from api.server import PROTOCOL

    return {"log_level": "info", "timeout_graceful_shutdown": 10, "http": PROTOCOL,
            "timeout_keep_alive": int(settings.keep_alive_seconds), "limit_concurrency": settings.max_connections,
            "h11_max_incomplete_event_size": settings.max_header_bytes, "server_header": False}


@click.command("worker")
@click.option("--burst", is_flag=True, help="Exit when the queue is empty.")
@click.option("--name", default=None, help="Worker name (default host:pid:random).")
def worker_command(burst: bool, name: str | None) -> None:
    """Consume jobs from the Redis queue (REDIS_URL is required)."""
    from services.runtime import build_runtime
    from services.settings import get_settings
    from worker.main import make_worker

    settings = get_settings()
    if not settings.redis_url:
        raise click.ClickException("ndrf worker needs REDIS_URL; without Redis, 'ndrf serve' runs jobs itself")
    runtime = build_runtime(settings)
    if not burst:
        runtime.start_experiment_scheduler()   # admits experiment runs even while no API process is up
    reason = make_worker(runtime, name).work(burst=burst, install_signals=True)
    click.echo(f"worker exited: {reason}", err=True)

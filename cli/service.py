"""``ndrf serve`` and ``ndrf worker``: the service's two processes (both read REDIS_URL and NDRF_STORE)."""

from __future__ import annotations

import logging

import click

log = logging.getLogger(__name__)


@click.command("serve")
@click.option("--host", default="127.0.0.1", show_default=True, help="Interface to bind.")
@click.option("--port", default=8000, show_default=True, type=click.IntRange(1, 65535), help="Port.")
def serve_command(host: str, port: int) -> None:
    """Run the HTTP API and the dashboard. Without REDIS_URL, jobs run in this process."""
    import uvicorn

    from api.app import create_app
    from services.settings import get_settings

    settings = get_settings()
    click.echo(f"ndrf serve on http://{host}:{port} (store {settings.store}, "
               f"{'redis ' + settings.redis_url if settings.redis_url else 'embedded workers'})", err=True)
    uvicorn.run(create_app(settings), host=host, port=port, log_level="info", timeout_graceful_shutdown=10)


@click.command("worker")
@click.option("--burst", is_flag=True, help="Exit when the queue is empty.")
@click.option("--name", default=None, help="Worker name (default host:pid:random).")
def worker_command(burst: bool, name: str | None) -> None:
    """Consume jobs from the Redis queue (REDIS_URL is required)."""
    from services.runtime import build_runtime
    from services.settings import get_settings
    from worker.main import Worker

    settings = get_settings()
    if not settings.redis_url:
        raise click.ClickException("ndrf worker needs REDIS_URL; without Redis, 'ndrf serve' runs jobs itself")
    runtime = build_runtime(settings)
    worker = Worker(runtime.service, runtime.queue, runtime.events, lease_seconds=settings.lease_seconds,
                    max_attempts=settings.max_attempts, name=name, reconcile=runtime.reconcile_periodically)
    reason = worker.work(burst=burst, install_signals=True)
    click.echo(f"worker exited: {reason}", err=True)


@click.command("bench", context_settings={"ignore_unknown_options": True, "help_option_names": []})
@click.argument("args", nargs=-1, type=click.UNPROCESSED)
def bench_command(args: tuple[str, ...]) -> None:
    """What accuracy costs in time (same as python -m bench; --quick runs in under 10 minutes)."""
    from bench.__main__ import main

    main(list(args))

"""Embedded mode: a runner thread that dies is restarted by the runtime's supervisor, and /healthz
reports the restart (503 while a runner is down, then ok with the count)."""

from __future__ import annotations

import threading

from fastapi.testclient import TestClient

from harness.cluster import wait_until
from services.runtime import build_runtime
from services.settings import Settings


class _Flaky:
    """A worker whose first incarnation dies at once (a bug escaping its loop); later ones wait."""

    deaths = 0

    def __init__(self):
        self.stopping = threading.Event()

    def work(self):
        if _Flaky.deaths == 0:
            _Flaky.deaths += 1
            raise RuntimeError("a bug outside any job")
        self.stopping.wait()

    def request_stop(self):
        self.stopping.set()


def test_a_dead_embedded_runner_is_restarted_and_reported(tmp_path):
    runtime = build_runtime(Settings(store=str(tmp_path / "store")))
    try:
        runtime.start_embedded_workers(lambda rt, name: _Flaky(), check_every=0.05)
        wait_until(lambda: runtime.runner_restarts == 1, 10, what="the restart")
        assert runtime.runner_failure == "RuntimeError: a bug outside any job"
        wait_until(lambda: all(t.is_alive() for t in runtime.threads), 5, what="a live runner")
    finally:
        runtime.stop(timeout=5)


def test_healthz_reports_runner_restarts(tmp_path, monkeypatch):
    from api.app import create_app

    _Flaky.deaths = 0
    monkeypatch.setattr("worker.main.make_worker", lambda rt, name: _Flaky())
    app = create_app(Settings(store=str(tmp_path / "store")))
    with TestClient(app) as client:
        runtime = app.state.runtime
        wait_until(lambda: runtime.runner_restarts == 1 and all(t.is_alive() for t in runtime.threads), 10,
                   what="the restart")
        health = client.get("/healthz").json()
        assert health["status"] == "ok" and health["runner_restarts"] == 1 and "restart" in health["detail"]

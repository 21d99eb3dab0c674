"""Shared fixtures, and the test tiers. Mitsuba's variant is selected once per session, lazily.

The tiers are folders (``tests/unit``, ``tests/service``, ``tests/e2e``); every test in one is
marked with its name, so ``pytest -m unit`` runs a tier whatever paths are given. Helpers live in
``tests/support`` and are imported by absolute name, so moving a test file between tiers is a
``git mv`` and nothing else.
"""

from __future__ import annotations

import signal
from pathlib import Path

import pytest

from harness.cluster import Process, Redis, start_api
from tests.support.service import open_test_store

#: Tier folder -> what its tests run against (the marker and its description).
TIERS = {
    "unit": "in-process: the solver, the schemas and the service's logic, no server process",
    "service": "the service's parts against real infrastructure: Redis, the stores, sandboxed children",
    "e2e": "real ndrf serve / ndrf worker / CLI processes, the dashboard in Chromium, faults",
}
TESTS = Path(__file__).resolve().parent


def pytest_configure(config: pytest.Config) -> None:
    for tier, what in TIERS.items():
        config.addinivalue_line("markers", f"{tier}: {what}")


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        parts = Path(str(item.path)).resolve().relative_to(TESTS).parts
        if len(parts) > 1 and parts[0] in TIERS:
            item.add_marker(getattr(pytest.mark, parts[0]))


@pytest.fixture(scope="session")
def mi():
    from services.solver.backend import use_mitsuba, use_torch

    use_torch()
    return use_mitsuba()


@pytest.fixture(scope="module")
def browser():
    """A headless Chromium per dashboard test module (``tests/support/browser.py``). Module scope, not
    session: Playwright's sync API keeps an event loop running in this thread while it is open,
    and later tests call ``asyncio.run``."""
    from playwright.sync_api import sync_playwright

    from tests.support.browser import ARGS, CHROMIUM

    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=str(CHROMIUM), args=ARGS)
        yield browser
        browser.close()


@pytest.fixture(scope="session")
def s3_server():
    """moto's S3 server on loopback, in a child process, for the whole session (tests/support/s3server.py)."""
    from harness.s3server import S3Server

    server = S3Server().start()
    yield server
    server.stop()


@pytest.fixture
def s3_store(s3_server):
    """An S3Store on a fresh prefix of the session's bucket."""
    import uuid

    from harness.s3server import ACCESS_KEY, REGION, SECRET_KEY
    from services.store.s3 import S3Store

    store = S3Store(f"s3://ndrf/t-{uuid.uuid4().hex[:12]}", endpoint=s3_server.endpoint, access_key_id=ACCESS_KEY,
                    secret_access_key=SECRET_KEY, region=REGION)
    yield store
    store.close()


# ------------------------------------------------------------------ the service, in processes

@pytest.fixture()
def redis_server():
    server = Redis().start()
    yield server
    server.kill()


@pytest.fixture(params=["folder", "s3"])
def store_env(request, tmp_path):
    """Where the service keeps its artifacts: a folder (the embedded default) or a bucket of the
    moto S3 server on loopback (a fresh prefix per test: no folder is shared then)."""
    if request.param == "folder":
        return {"NDRF_STORE": str(tmp_path / "store")}
    return request.getfixturevalue("s3_server").env(prefix=f"t-{tmp_path.name}")


@pytest.fixture()
def stack(tmp_path, redis_server, store_env):
    """API + workers sharing one Redis and one store; ``add_worker()`` starts another worker, with
    a scratch folder of its own."""
    env = {"REDIS_URL": redis_server.url, "NDRF_LEASE_SECONDS": "3", "NDRF_SCRATCH": str(tmp_path / "scratch-api"),
           **store_env}
    processes = []

    class Stack:
        def __init__(self):
            self.env = env
            self.store = open_test_store(env)
            api_proc, self.api = start_api(tmp_path, env)
            processes.append(api_proc)
            self.workers = []

        def add_worker(self, name, **extra_env):
            worker = Process(["-v", "worker", "--name", name],
                             {**env, "NDRF_SCRATCH": str(tmp_path / f"scratch-{name}"), **extra_env},
                             tmp_path / f"{name}.log")
            processes.append(worker)
            self.workers.append(worker)
            return worker

    yield Stack()
    for proc in processes:      # no graceful shutdown here: a worker would first finish its iteration
        proc.kill(signal.SIGKILL)

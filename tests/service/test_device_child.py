"""The device of the service's children (services/jobs/device.py): a sandboxed child resolves
NDRF_DEVICE under its limits, and /healthz and /metrics name what it found.

On a GPU machine (bench/gpu_check.sh runs this file with NDRF_DEVICE=cuda) the first test is the
check that CUDA starts inside a child: its limits (services/jobs/isolation.py, memory_limit) and its
sandbox allow it.
"""

from __future__ import annotations

import resource

import pytest
from fastapi.testclient import TestClient

from harness.cluster import wait_until
from services.settings import Settings, get_settings


def test_a_sandboxed_child_runs_on_the_device_asked_for():
    from services.jobs.device import probe_device

    described = probe_device()
    requested = get_settings().device
    assert described["device"] in ("cpu", "cuda"), described
    assert described["requested"] == requested and described["reason"], described
    if requested != "auto":
        assert described["device"] == requested, described


@pytest.mark.parametrize(("device", "nvidia", "limit"), [
    ("cpu", False, resource.RLIMIT_AS), ("auto", False, resource.RLIMIT_AS), ("cuda", False, resource.RLIMIT_AS),
    ("cpu", True, resource.RLIMIT_AS), ("auto", True, resource.RLIMIT_DATA), ("cuda", True, resource.RLIMIT_DATA)])
def test_the_memory_limit_leaves_cuda_room_to_start_only_where_it_may(device, nvidia, limit):
    from services.jobs.isolation import memory_limit

    assert memory_limit(device, nvidia) == limit


def test_the_child_environment_carries_the_device_and_the_visible_gpus(monkeypatch):
    from services.jobs.isolation import _environment

    monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "1")
    monkeypatch.setenv("NDRF_DEVICE", "cpu")
    get_settings.cache_clear()
    try:
        env = _environment()
    finally:
        get_settings.cache_clear()
    assert env["NDRF_DEVICE"] == "cpu" and env["CUDA_VISIBLE_DEVICES"] == "1"


def test_healthz_and_metrics_name_the_device(tmp_path):
    from api.app import create_app

    app = create_app(Settings(store=str(tmp_path / "store"), metrics_public=True))
    with TestClient(app) as client:
        client.get("/healthz")
        wait_until(lambda: client.get("/healthz").json()["device"] is not None, 60, what="the device probe")
        device = client.get("/healthz").json()["device"]
        assert device["device"] in ("cpu", "cuda") and device["requested"] == get_settings().device, device
        metrics = client.get("/metrics").text
    line = next(line for line in metrics.splitlines() if line.startswith("ndrf_device_info{"))
    assert f'device="{device["device"]}"' in line and line.endswith(" 1.0"), line

"""The service under test in processes: a real Redis, a real ``ndrf serve`` (uvicorn) and ``ndrf
worker`` (:mod:`tests.support.cluster`), a JSON client of the API with headers, the store those
processes use, and a small job."""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from pathlib import Path

from tests.support.cluster import ROOT, Process, Redis, free_port, wait_until

__all__ = ["ROOT", "Api", "Process", "RedisServer", "open_test_store", "read_sse", "small_job", "start_api",
           "wait_until"]


class RedisServer(Redis):
    """A throw-away redis-server without persistence (so a restart loses everything)."""

    stop = Redis.kill


class Api:
    def __init__(self, base: str, key: str | None = None):
        self.base, self.key = base, key

    def request(self, method: str, path: str, body=None, headers=None, raw: bytes | None = None):
        data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers={"Content-Type": "application/json", **(headers or {})})
        if self.key:
            req.add_header("Authorization", f"Bearer {self.key}")
        try:
            with urllib.request.urlopen(req, timeout=60) as resp:
                return resp.status, dict(resp.headers), resp.read()
        except urllib.error.HTTPError as err:
            return err.code, dict(err.headers), err.read()

    def json(self, method: str, path: str, body=None, headers=None):
        status, head, data = self.request(method, path, body, headers)
        return status, head, (json.loads(data) if data else None)

    def wait_status(self, job_id: str, statuses, timeout: float):
        def done():
            _, _, job = self.json("GET", f"/v1/jobs/{job_id}")
            return job if job and job["status"] in statuses else None
        return wait_until(done, timeout, 0.2, what=f"job {job_id} in {statuses}")


def start_api(tmp: Path, env: dict[str, str]) -> tuple[Process, Api]:
    port = free_port()
    proc = Process(["serve", "--port", str(port)], env, tmp / f"api-{port}.log")
    api = Api(f"http://127.0.0.1:{port}", env.get("NDRF_API_KEYS", "").split(",")[0] or None)

    def up():
        if proc.proc.poll() is not None:
            raise RuntimeError(f"ndrf serve exited:\n{proc.tail()}")
        try:
            return api.request("GET", "/healthz")[0] == 200
        except OSError:
            return False

    wait_until(up, 60, 0.2, what="ndrf serve")
    return proc, api


def open_test_store(env: dict[str, str]):
    """The store a service process started with ``env`` uses, opened in the test process."""
    from services.runtime import open_store
    from services.settings import Settings

    if env["NDRF_STORE"].startswith("s3://"):
        from services.store.s3 import S3Store

        return S3Store(env["NDRF_STORE"], endpoint=env["NDRF_S3_ENDPOINT"], access_key_id=env["AWS_ACCESS_KEY_ID"],
                       secret_access_key=env["AWS_SECRET_ACCESS_KEY"], region=env["AWS_REGION"])
    return open_store(Settings(store=env["NDRF_STORE"]))


def small_job(method="ndrf-lhs", iterations=6, **extra) -> dict:
    job = {
        "name": "service test",
        "scene": {"builtin": "cornell-box"},
        "parameters": [{"key": "red.reflectance.value", "init": [0.3, 0.3, 0.3]}],
        "targets": {"synthetic": {"values": {"red.reflectance.value": [0.57, 0.04, 0.04]}, "spp": 16}},
        "method": method,
        "iterations": iterations,
        "render": {"spp": 4, "gradient_spp": 4, "resolution": [16, 16]},
        "training": {"residual_points": 256, "incident_samples": 4, "warmup_steps": 10, "steps_per_iteration": 2},
        "checkpoint_every": 1,
        "seed": 1,
    }
    job.update(extra)
    return job


def read_sse(api, job_id, timeout=120.0, last_event_id=None):
    """All events of a job until its final status (the server closes the stream then)."""
    req = urllib.request.Request(f"{api.base}/v1/jobs/{job_id}/events")
    if last_event_id is not None:
        req.add_header("Last-Event-ID", str(last_event_id))
    if api.key:
        req.add_header("Authorization", f"Bearer {api.key}")
    events, current = [], {}
    with urllib.request.urlopen(req, timeout=timeout) as resp:
        assert resp.headers["Content-Type"].startswith("text/event-stream")
        for raw in resp:
            line = raw.decode().rstrip("\n")
            if line.startswith("data: "):
                current["data"] = json.loads(line[6:])
            elif line.startswith("id: "):
                current["id"] = int(line[4:])
            elif line == "" and "data" in current:
                events.append(current)
                current = {}
    return events

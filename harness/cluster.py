"""A service on this machine for the service tests and the benchmarks: a throw-away ``redis-server``
(no persistence, so a restart loses everything), ``ndrf serve`` and ``ndrf worker`` processes
sharing one store, each with its output in a log file, a JSON client of the API, and a job of a few
seconds. Loopback only."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]  # the checkout


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_until(predicate, timeout: float, interval: float = 0.1, what: str = "condition"):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(interval)
    raise TimeoutError(f"timed out after {timeout} s waiting for {what}")


class Redis:
    """``redis-server`` on a free port, without persistence."""

    def __init__(self, port: int | None = None):
        self.port = port or free_port()
        self.proc: subprocess.Popen | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def start(self) -> Redis:
        binary = shutil.which("redis-server")
        if binary is None:
            raise RuntimeError("redis-server is not installed (apt-get install redis-server)")
        self.proc = subprocess.Popen([binary, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
                                      "--appendonly", "no", "--maxclients", "10000"],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        import redis

        def up() -> bool:
            try:
                return bool(redis.Redis.from_url(self.url, socket_connect_timeout=0.5).ping())
            except redis.RedisError:
                return False

        wait_until(up, 10, what="redis")
        return self

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait()
            self.proc = None


class Process:
    """``python -m cli.main ARGS`` (optionally under ``taskset``), output in ``log``, in a session of
    its own. ``nice`` lowers the priority of the process *and of its session's autogroup*: with
    Linux's autogroup scheduling, sessions share the CPU fairly whatever their processes' nice, so
    ``nice -n 19`` alone leaves a worker in its own session as loud as the API next to it."""

    def __init__(self, args: list[str], env: dict[str, str], log: Path, prefix: list[str] | None = None,
                 nice: int = 0):
        self.args, self.log = args, log
        niced = ["nice", "-n", str(nice)] if nice else []
        self.proc = subprocess.Popen([*(prefix or []), *niced, sys.executable, "-m", "cli.main", *args], cwd=ROOT,
                                     env={**os.environ, **env}, stdout=log.open("ab"), stderr=subprocess.STDOUT,
                                     start_new_session=True)
        if nice > 0:  # without autogroup scheduling (no such file), nice alone does it
            with contextlib.suppress(OSError):
                Path(f"/proc/{self.proc.pid}/autogroup").write_text(f"{nice}\n")

    @property
    def pid(self) -> int:
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc.poll() is None

    def kill(self, sig: int = signal.SIGKILL, wait: float = 60) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(sig)
            try:
                self.proc.wait(timeout=wait)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()

    def tail(self, n: int = 40) -> str:
        return "\n".join(self.log.read_text(errors="replace").splitlines()[-n:])


class Api:
    """A JSON client of the API (urllib: no extra dependency), with the caller's key when given."""

    def __init__(self, base: str, key: str | None = None):
        self.base, self.key = base, key

    def request(self, method: str, path: str, body=None, headers=None, raw: bytes | None = None,
                timeout: float = 60) -> tuple[int, dict, bytes]:
        """``(status, headers, body bytes)``; an HTTP error status is returned, not raised."""
        data = raw if raw is not None else (json.dumps(body).encode() if body is not None else None)
        req = urllib.request.Request(self.base + path, data=data, method=method,
                                     headers={"Content-Type": "application/json", **(headers or {})})
        if self.key:
            req.add_header("Authorization", f"Bearer {self.key}")
        try:
            with urllib.request.urlopen(req, timeout=timeout) as resp:
                return resp.status, dict(resp.headers), resp.read()
        except urllib.error.HTTPError as err:
            return err.code, dict(err.headers), err.read()

    def json(self, method: str, path: str, body=None, headers=None, timeout: float = 60):
        """``(status, headers, parsed body or None)``."""
        status, head, data = self.request(method, path, body, headers, timeout=timeout)
        return status, head, (json.loads(data) if data else None)

    def wait_status(self, job_id: str, statuses, timeout: float):
        def done():
            _, _, job = self.json("GET", f"/v1/jobs/{job_id}")
            return job if job and job["status"] in statuses else None
        return wait_until(done, timeout, 0.2, what=f"job {job_id} in {statuses}")


def start_api(folder: Path, env: dict[str, str], port: int | None = None, prefix: list[str] | None = None,
              name: str = "api", extra: list[str] | None = None) -> tuple[Process, Api]:
    """``ndrf serve`` on ``port`` (a free one by default), once it answers ``/healthz``; its client
    uses the first key of ``NDRF_API_KEYS``."""
    port = port or free_port()
    proc = Process(["serve", "--port", str(port), *(extra or [])], env, folder / f"{name}-{port}.log", prefix)
    api = Api(f"http://127.0.0.1:{port}", env.get("NDRF_API_KEYS", "").split(",")[0] or None)

    def up() -> bool:
        if not proc.alive():
            raise RuntimeError(f"ndrf serve exited:\n{proc.tail()}")
        try:
            return api.request("GET", "/healthz", timeout=5)[0] == 200
        except OSError:
            return False

    wait_until(up, 90, 0.2, what="ndrf serve")
    return proc, api


def start_worker(folder: Path, env: dict[str, str], name: str, prefix: list[str] | None = None,
                 nice: int = 0) -> Process:
    return Process(["-v", "worker", "--name", name], env, folder / f"{name}.log", prefix, nice=nice)


def small_job(method: str = "ndrf-lhs", iterations: int = 6, seed: int = 1, **extra) -> dict:
    """A job of a few seconds per attempt: Cornell box, one albedo, 16x16, checkpoint every iteration."""
    job = {
        "name": "small job",
        "scene": {"builtin": "cornell-box"},
        "parameters": [{"key": "red.reflectance.value", "init": [0.3, 0.3, 0.3]}],
        "targets": {"synthetic": {"values": {"red.reflectance.value": [0.57, 0.04, 0.04]}, "spp": 16}},
        "method": method,
        "iterations": iterations,
        "render": {"spp": 4, "gradient_spp": 4, "resolution": [16, 16]},
        "training": {"residual_points": 256, "incident_samples": 4, "warmup_steps": 10, "steps_per_iteration": 2},
        "checkpoint_every": 1,
        "seed": seed,
    }
    job.update(extra)
    return job

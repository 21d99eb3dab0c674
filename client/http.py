"""The HTTP client: bearer key, RFC 9457 problems as :class:`ApiError`, JSON, downloads, SSE."""

from __future__ import annotations

import json
import os
import re
import shutil
import time
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from client.sse import parse_stream

JOB_ID = re.compile(r"^[0-9a-f]{20}$")
EXPERIMENT_ID = re.compile(r"^e[0-9a-f]{20}$")
FINISHED = frozenset({"succeeded", "failed", "canceled"})
#: Answers that mean "not now" (a stream cap, a busy upload guard, Redis unreachable): retried after
#: their ``Retry-After`` when retrying cannot do anything twice (module docstring of :class:`Client`).
RETRIED = frozenset({429, 503})
#: The longest ``Retry-After`` the client waits for before giving up with the answer.
MAX_RETRY_AFTER = 30.0


def is_job_id(value: str) -> bool:
    return bool(JOB_ID.match(value or ""))


def is_experiment_id(value: str) -> bool:
    return bool(EXPERIMENT_ID.match(value or ""))


class ApiError(Exception):
    """A non-2xx answer: ``status``, the problem document, and its ``errors`` [{field, message}]."""

    def __init__(self, status: int, problem: dict, headers: dict[str, str] | None = None):
        self.status, self.problem = status, problem
        self.headers = {k.lower(): v for k, v in (headers or {}).items()}   # names are case-insensitive
        self.errors: list[dict] = problem.get("errors") or []
        super().__init__(f"HTTP {status}: {problem.get('detail') or problem.get('title') or 'error'}")

    def lines(self) -> list[str]:
        """One line per offending field (or the detail)."""
        if self.errors:
            return [f"{e.get('field')}: {e.get('message')}" for e in self.errors]
        return [str(self.problem.get("detail") or self.problem.get("title") or f"HTTP {self.status}")]


def _retry_after(value: str | None) -> float | None:
    """Seconds of a ``Retry-After`` given in seconds, when short enough to wait for; else None."""
    try:
        seconds = float(value) if value is not None else None
    except ValueError:
        return None   # an HTTP date: the server means a long time
    return seconds if seconds is not None and 0 <= seconds <= MAX_RETRY_AFTER else None


class Client:
    """The API over HTTP. A 429 or 503 with ``Retry-After`` (at most :data:`MAX_RETRY_AFTER` s) is
    retried up to ``retries`` times after the wait it names, for requests that cannot take effect
    twice: reads (GET) and writes that carry an ``Idempotency-Key``. Anything else is an
    :class:`ApiError` at once."""

    def __init__(self, base_url: str, api_key: str | None = None, timeout: float = 60.0, retries: int = 3):
        if retries < 0:
            raise ValueError(f"retries must be >= 0, got {retries}")
        self.base = base_url.rstrip("/")
        self.api_key = api_key or None
        self.timeout = timeout
        self.retries = retries

    @classmethod
    def from_env(cls, server: str | None = None, **kwargs) -> Client:
        """``server`` (default ``NDRF_SERVER``, else http://127.0.0.1:8000) and the key in ``NDRF_API_KEY``."""
        url = server or os.environ.get("NDRF_SERVER") or "http://127.0.0.1:8000"
        return cls(url, os.environ.get("NDRF_API_KEY"), **kwargs)

    # ---------------------------------------------------------------- transport

    def _open(self, method: str, path: str, body: Any = None, headers: dict | None = None, timeout: float | None = None):
        safe = method == "GET" or "Idempotency-Key" in (headers or {})
        for attempt in range(self.retries + 1):
            try:
                return self._open_once(method, path, body, headers, timeout)
            except ApiError as err:
                wait = _retry_after(err.headers.get("retry-after")) if err.status in RETRIED else None
                if not safe or wait is None or attempt == self.retries:
                    raise
                time.sleep(wait)
        raise AssertionError("unreachable")

    def _open_once(self, method: str, path: str, body: Any = None, headers: dict | None = None,
                   timeout: float | None = None):
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(self.base + path, data=data, method=method,
                                         headers={"Accept": "application/json", **(headers or {})})
        if data is not None:
            request.add_header("Content-Type", "application/json")
        if self.api_key:
            request.add_header("Authorization", f"Bearer {self.api_key}")
        try:
            return urllib.request.urlopen(request, timeout=timeout or self.timeout)
        except urllib.error.HTTPError as err:
            raw = err.read()
            try:
                problem = json.loads(raw) if raw else {}
            except ValueError:
                problem = {"detail": raw[:500].decode(errors="replace")}
            raise ApiError(err.code, problem if isinstance(problem, dict) else {"detail": str(problem)},
                           dict((err.headers or {}).items())) from None

    def request(self, method: str, path: str, body: Any = None, headers: dict | None = None) -> bytes:
        with self._open(method, path, body, headers) as response:
            return response.read()

    def get(self, path: str, **query) -> Any:
        params = {k: v for k, v in query.items() if v is not None}
        suffix = f"?{urllib.parse.urlencode(params)}" if params else ""
        raw = self.request("GET", path + suffix)
        return json.loads(raw) if raw else None

    def post(self, path: str, body: Any = None, headers: dict | None = None) -> Any:
        raw = self.request("POST", path, {} if body is None else body, headers)
        return json.loads(raw) if raw else None

    def download(self, path: str, destination: str | Path) -> Path:
        """Stream one resource into a file (written whole, then renamed)."""
        destination = Path(destination)
        destination.parent.mkdir(parents=True, exist_ok=True)
        partial = destination.with_name(destination.name + ".part")
        with self._open("GET", path, headers={"Accept": "*/*"}) as response, partial.open("wb") as out:
            shutil.copyfileobj(response, out, 1 << 16)
        partial.replace(destination)
        return destination

    # --------------------------------------------------------------------- jobs

    def submit_job(self, job: dict, idempotency_key: str | None = None) -> dict:
        headers = {"Idempotency-Key": idempotency_key} if idempotency_key else None
        return self.post("/v1/jobs", job, headers)

    def job(self, job_id: str) -> dict:
        return self.get(f"/v1/jobs/{job_id}")

    def jobs(self, status: str | None = None, limit: int = 50) -> list[dict]:
        return self.get("/v1/jobs", status=status, limit=limit)["items"]

    def iterations(self, job_id: str, after: int = -1) -> list[dict]:
        return self.get(f"/v1/jobs/{job_id}/iterations", after=after)

    def cancel(self, resource_id: str) -> dict:
        return self.post(f"{self.path_of(resource_id)}/cancel")

    def request_images(self, job_id: str) -> dict:
        """The running job writes every view's render and its gradient images at its next iteration."""
        return self.post(f"/v1/jobs/{job_id}/images")

    # -------------------------------------------------------------- experiments

    def submit_experiment(self, spec: dict) -> dict:
        return self.post("/v1/experiments", spec)

    def submit(self, document: dict) -> tuple[str, dict]:
        """A job file or an experiment file (it has a ``base``): ``("job"|"experiment", accepted)``."""
        if "base" in document:
            return "experiment", self.submit_experiment(document)
        return "job", self.submit_job(document)

    def experiment(self, exp_id: str) -> dict:
        return self.get(f"/v1/experiments/{exp_id}")

    def experiments(self, limit: int = 50) -> list[dict]:
        return self.get("/v1/experiments", limit=limit)["items"]

    def runs(self, exp_id: str) -> list[dict]:
        return self.get(f"/v1/experiments/{exp_id}/runs")

    def results_csv(self, exp_id: str) -> str:
        return self.request("GET", f"/v1/experiments/{exp_id}/results.csv").decode()

    def curves(self, exp_id: str) -> dict:
        return self.get(f"/v1/experiments/{exp_id}/curves")

    def retry(self, exp_id: str) -> dict:
        return self.post(f"/v1/experiments/{exp_id}/retry")

    def append(self, exp_id: str, *, grid: dict | None = None, seeds: list[int] | None = None,
               samples: int = 0) -> dict:
        return self.post(f"/v1/experiments/{exp_id}/runs", {"grid": grid or {}, "seeds": seeds or [],
                                                             "samples": samples})

    # ------------------------------------------------------------------- events

    @staticmethod
    def path_of(resource_id: str) -> str:
        if is_experiment_id(resource_id):
            return f"/v1/experiments/{resource_id}"
        if is_job_id(resource_id):
            return f"/v1/jobs/{resource_id}"
        raise ValueError(f"{resource_id!r} is neither a job id (20 hex) nor an experiment id ('e' + 20 hex)")

    def status(self, resource_id: str) -> str:
        return self.get(self.path_of(resource_id))["status"]

    def events(self, resource_id: str, after: int = 0, retries: int = 20) -> Iterator[dict]:
        """Every event of a job or an experiment after ``after``, live, until it finishes. A
        dropped connection is resumed with ``Last-Event-ID`` (up to ``retries`` times in a row)."""
        last, failures = after, 0
        path = f"{self.path_of(resource_id)}/events"
        while True:
            got_any = False
            try:
                with self._open("GET", path, headers={"Accept": "text/event-stream", "Last-Event-ID": str(last)},
                                timeout=max(self.timeout, 60.0)) as response:
                    for event in parse_stream(response):
                        got_any, failures = True, 0
                        last = max(last, int(event.get("seq", last)))
                        yield event
                        final = event.get("type") == "status" and event.get("status") in FINISHED
                        if final and self.status(resource_id) in FINISHED:
                            return
            except ApiError:
                raise
            except (OSError, ValueError):   # dropped (server restart, network): resume where it stopped
                failures += 1
                if failures > retries:
                    raise
                time.sleep(min(5.0, 0.5 * failures))
                continue
            if not got_any and self.status(resource_id) in FINISHED:
                return                      # the server ended the stream: nothing more will come

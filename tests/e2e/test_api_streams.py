"""The per-key stream cap of issue 27 (points 3 and 4) against real ``ndrf serve`` processes in Redis
mode: streams opened with a key and with the read tokens it was given, on two API processes, never
add up to more than the cap; a Redis that cannot answer refuses streams (503 + ``Retry-After``)."""

from __future__ import annotations

import http.client
import signal
from urllib.parse import urlsplit

import pytest

from harness.cluster import Api, small_job, start_api, wait_until

CAP = 3


def _open(api: Api, path: str, key: str | None):
    """Open an event stream and keep it open: (status, headers, connection)."""
    url = urlsplit(api.base)
    conn = http.client.HTTPConnection(url.hostname, url.port, timeout=30)
    conn.request("GET", path, headers={"Authorization": f"Bearer {key}"} if key else {})
    resp = conn.getresponse()
    if resp.status == 200:
        assert resp.readline().startswith(b"retry:")              # the stream is really open
    else:
        resp.read()
    return resp.status, resp.headers, conn  # (case-insensitive)


@pytest.fixture()
def two_apis(tmp_path, redis_server):
    env = {"REDIS_URL": redis_server.url, "NDRF_STORE": str(tmp_path / "store"), "NDRF_API_KEYS": "tenant-a,tenant-b",
           "NDRF_MAX_STREAMS_PER_KEY": str(CAP), "NDRF_SCRATCH": str(tmp_path / "scratch")}
    procs = []
    try:
        for _ in range(2):
            proc, api = start_api(tmp_path, env)
            procs.append((proc, api))
        yield [api for _, api in procs], redis_server
    finally:
        for proc, _ in procs:
            proc.kill(signal.SIGKILL)


def test_streams_per_key_never_exceed_the_cap_across_tokens_and_api_processes(two_apis):
    """Key A opens streams of its job with its bearer key and with the job's read token, alternately
    on two API processes: exactly ``CAP`` are let in, the rest get 429 with ``Retry-After``, and so
    do streams of its experiment opened with the experiment's token; key B, meanwhile, still opens
    its own. Closing one of A's frees one place."""
    (first, second), _ = two_apis
    a = Api(first.base, "tenant-a")
    status, _, job = a.json("POST", "/v1/jobs", _job())
    assert status == 202, job
    token = a.json("GET", f"/v1/jobs/{job['id']}")[2]["read_token"]
    path = f"/v1/jobs/{job['id']}/events"
    opened = []
    try:
        results = []
        for i in range(4 * CAP):
            api = (first, second)[i % 2]
            by_token = i % 3 != 0
            status, headers, conn = _open(api, f"{path}?token={token}" if by_token else path,
                                          None if by_token else "tenant-a")
            opened.append(conn)
            results.append((status, by_token, headers.get("Retry-After")))
        assert [s for s, _, _ in results].count(200) == CAP, results
        assert {s for s, _, _ in results} == {200, 429}, results
        assert all(r for s, _, r in results if s == 429), results
        assert any(t for s, t, _ in results if s == 429) and any(not t for s, t, _ in results if s == 429)
        status, _, experiment = a.json("POST", "/v1/experiments", {"base": _job(), "grid": {"learning_rate": [0.08]}})
        assert status == 202, experiment
        exp_token = a.json("GET", f"/v1/experiments/{experiment['id']}")[2]["read_token"]
        for api in (first, second):                                # experiment streams count too
            status, headers, conn = _open(api, f"/v1/experiments/{experiment['id']}/events?token={exp_token}", None)
            opened.append(conn)
            assert status == 429 and headers.get("Retry-After"), status
        b = Api(second.base, "tenant-b")
        status, _, other = b.json("POST", "/v1/jobs", _job())
        assert status == 202
        status, _, conn = _open(first, f"/v1/jobs/{other['id']}/events", "tenant-b")
        opened.append(conn)
        assert status == 200                                       # another key: its own cap
        first_open = next(conn for conn, (s, _, _) in zip(opened, results, strict=False) if s == 200)
        first_open.close()
        opened.remove(first_open)

        def one_more():
            status, _, conn = _open(second, f"{path}?token={token}", None)
            opened.append(conn)
            return status == 200
        wait_until(one_more, 10, 0.3, what="a place freed by a closed stream")
        status, _, conn = _open(first, path, "tenant-a")
        opened.append(conn)
        assert status == 429
    finally:
        for conn in opened:
            conn.close()


def test_a_stream_is_refused_with_503_when_redis_cannot_count(two_apis):
    """Redis stopped: the count of open streams cannot be read, so a stream is refused with 503 and
    ``Retry-After``, not let in uncapped."""
    (first, _), redis_server = two_apis
    a = Api(first.base, "tenant-a")
    status, _, job = a.json("POST", "/v1/jobs", _job())
    assert status == 202, job
    redis_server.kill()
    status, headers, conn = _open(first, f"/v1/jobs/{job['id']}/events", "tenant-a")
    conn.close()
    assert status == 503 and headers.get("Retry-After"), (status, headers)


def _job() -> dict:
    return small_job()

"""Issue 27's request defences in-process (the app on a TestClient, embedded mode, API keys set):
authentication before the body, the cap on chunked bodies, the JSON limits, capped validation
errors, tokens that do not renew, /metrics for admins, no slash redirects, security headers. The
same attacks against a real server, with memory and /healthz measured: tests/e2e/test_adversarial.py."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from harness.cluster import small_job
from services.settings import Limits, Settings

ALICE = {"Authorization": "Bearer alice-key", "Content-Type": "application/json"}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    store = tmp_path_factory.mktemp("guard") / "store"
    settings = Settings(store=str(store), api_keys=["alice-key"], admin_keys=["admin-key"],
                        limits=Limits(upload_bytes=1 << 20, json_items=100, validation_errors=5))
    with TestClient(create_app(settings)) as client:
        yield client


def test_no_key_is_a_401_before_the_body_is_read(client):
    consumed = []

    def body():
        for _ in range(100):
            consumed.append(1)
            yield b" " * 65536

    answer = client.post("/v1/jobs", content=body())
    assert answer.status_code == 401 and answer.headers["www-authenticate"].startswith("Bearer")
    assert len(consumed) <= 2     # the client's first chunk at most: the server never read it
    assert client.post("/v1/experiments", content=b"{}", headers={"Authorization": "Bearer nope"}).status_code == 401


def test_bodies_over_the_cap_are_a_413_declared_or_chunked(client):
    declared = client.post("/v1/jobs", content=b" " * ((1 << 20) + 1), headers=ALICE)
    assert declared.status_code == 413 and "NDRF_MAX_UPLOAD_BYTES" in declared.json()["detail"]
    streamed = client.post("/v1/jobs", content=(b" " * 65536 for _ in range(20)), headers=ALICE)
    assert streamed.status_code == 413 and streamed.json()["type"] == "/problems/too-large"


def test_json_limits_are_named_and_validation_errors_capped(client):
    job = small_job()
    job["targets"]["synthetic"]["values"]["red.reflectance.value"] = ["x"] * 101
    answer = client.post("/v1/jobs", content=json.dumps(job), headers=ALICE)
    assert answer.status_code == 413 and "NDRF_MAX_JSON_ITEMS" in answer.json()["detail"]
    job["targets"]["synthetic"]["values"]["red.reflectance.value"] = ["x"] * 90
    answer = client.post("/v1/jobs", content=json.dumps(job), headers=ALICE)
    problem = answer.json()
    assert answer.status_code == 422 and len(problem["errors"]) == 5 and problem["more_errors"] > 80
    assert "more error(s) not listed" in problem["detail"]
    assert client.post("/v1/jobs", content=b"{nope", headers=ALICE).status_code == 422


def test_a_token_request_gets_no_new_token(client):
    status = client.post("/v1/jobs", content=json.dumps(small_job("direct", iterations=1)), headers=ALICE)
    assert status.status_code == 202, status.text
    job_id = status.json()["id"]
    token = client.get(f"/v1/jobs/{job_id}", headers=ALICE).json()["read_token"]
    assert token
    assert client.get(f"/v1/jobs/{job_id}", params={"token": token}).json()["read_token"] is None
    client.post(f"/v1/jobs/{job_id}/cancel", headers=ALICE)


def test_metrics_slashes_and_headers(client):
    assert client.get("/metrics").status_code == 401
    assert client.get("/metrics", headers=ALICE).status_code == 403
    assert client.get("/metrics", headers={"Authorization": "Bearer admin-key"}).status_code == 200
    slash = client.get("/v1/jobs/", headers={**ALICE, "Host": "evil.example"}, follow_redirects=False)
    assert slash.status_code == 404 and "location" not in slash.headers
    page = client.get("/")
    assert page.headers["x-frame-options"] == "DENY" and page.headers["x-content-type-options"] == "nosniff"
    assert "script-src 'self'" in page.headers["content-security-policy"]
    assert client.get("/v1/jobs", headers=ALICE).headers["content-security-policy"].startswith("default-src 'none'")


def test_concurrent_bodies_share_one_memory_budget(tmp_path):
    """Bodies held at once count against NDRF_MAX_BODY_MEMORY_BYTES: a body that would go over is a
    503 with Retry-After (declared), and the bytes are given back when a request is answered."""
    import anyio

    from api.guard import Guard

    settings = Settings(store=str(tmp_path), limits=Limits(upload_bytes=1 << 20, body_memory_bytes=1 << 20))
    answers: list[int] = []
    release = anyio.Event()

    async def app(scope, receive, send):
        while (await receive()).get("more_body"):
            pass
        await release.wait()
        await send({"type": "http.response.start", "status": 200, "headers": []})
        await send({"type": "http.response.body", "body": b""})

    guard = Guard(app, settings)

    async def request(length: int):
        messages = [{"type": "http.request", "body": b" " * length, "more_body": False}]

        async def receive():
            return messages.pop(0) if messages else {"type": "http.disconnect"}

        async def send(message):
            if message["type"] == "http.response.start":
                answers.append(message["status"])

        scope = {"type": "http", "method": "POST", "path": "/v1/jobs",
                 "headers": [(b"content-length", str(length).encode())]}
        await guard(scope, receive, send)

    async def main():
        async with anyio.create_task_group() as tasks:
            tasks.start_soon(request, 700 << 10)
            await anyio.sleep(0.05)
            await request(700 << 10)            # 1.4 MiB held at once: refused at once
            assert guard.held == 700 << 10
            release.set()
        assert guard.held == 0
        await request(700 << 10)                # given back: accepted again

    anyio.run(main)
    assert answers == [503, 200, 200]

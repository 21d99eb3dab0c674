"""The service end to end: real ``ndrf serve`` (uvicorn) and ``ndrf worker`` processes against a
real Redis server started by the tests (no persistence, so it can be restarted empty)."""

from __future__ import annotations

import json
import signal
import time
import urllib.request

import numpy as np

from tests.service import small_job, start_api, wait_until


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


def test_embedded_submit_stream_succeed_and_fetch_images(tmp_path, store_env):
    proc, api = start_api(tmp_path, store_env)
    try:
        status, headers, accepted = api.json("POST", "/v1/jobs", small_job())
        assert status == 202 and headers["location"] == f"/v1/jobs/{accepted['id']}"
        job_id = accepted["id"]
        events = read_sse(api, job_id)
        kinds = [e["data"]["type"] for e in events]
        assert kinds.count("iteration") == 6 and events[-1]["data"]["status"] == "succeeded"
        assert [e["id"] for e in events] == sorted(e["id"] for e in events)

        replay = read_sse(api, job_id, last_event_id=events[3]["id"])      # reconnect: only what was missed
        assert [e["id"] for e in replay] == [e["id"] for e in events[4:]]

        _, _, job = api.json("GET", f"/v1/jobs/{job_id}")
        assert job["status"] == "succeeded" and job["iteration"] == 5 and job["plan"]["method"] == "ndrf-lhs"
        _, _, records = api.json("GET", f"/v1/jobs/{job_id}/iterations")
        assert [r["iteration"] for r in records] == list(range(6))
        status, headers, png = api.request("GET", f"/v1/jobs/{job_id}/iterations/5/gradients/0.png")
        assert status == 200 and headers["content-type"] == "image/png" and png[:4] == b"\x89PNG"
        status, _, npy = api.request("GET", f"/v1/jobs/{job_id}/iterations/5/gradients/2.npy")
        import io

        assert status == 200 and np.load(io.BytesIO(npy)).shape == (16, 16, 3)
        assert api.request("GET", f"/v1/jobs/{job_id}/iterations/5/render.png")[0] == 200
        assert api.request("GET", f"/v1/jobs/{job_id}/checkpoints/latest")[0] == 200
        status, headers, problem = api.json("GET", f"/v1/jobs/{job_id}/iterations/99/render.png")
        assert status == 404 and headers["content-type"] == "application/problem+json" and problem["status"] == 404
    finally:
        proc.kill(signal.SIGTERM)


def test_an_auto_job_says_what_it_picked_through_the_api(tmp_path, store_env):
    """``"method": "auto"`` over HTTP: the trial is announced on the stream, the record keeps what
    was asked, the plan says what ran and why."""
    proc, api = start_api(tmp_path, store_env)
    try:
        status, _, accepted = api.json("POST", "/v1/jobs", small_job("auto", iterations=2))
        assert status == 202
        events = [e["data"] for e in read_sse(api, accepted["id"], timeout=300)]
        kinds = [e["type"] for e in events]
        assert "auto" in kinds and kinds.index("auto") < kinds.index("plan") and events[-1]["status"] == "succeeded"
        _, _, job = api.json("GET", f"/v1/jobs/{accepted['id']}")
        assert job["method"] == "auto"
        assert job["plan"]["method"] == job["plan"]["auto"]["picked"] in ("prb", "ndrf-lhs", "ndrf-rhs")
        assert "predicted fastest" in job["plan"]["auto"]["reason"]
    finally:
        proc.kill(signal.SIGTERM)


def test_idempotent_resubmission_returns_the_same_job(stack):
    api = stack.api
    first = api.json("POST", "/v1/jobs", small_job(), {"Idempotency-Key": "retry-me"})
    again = api.json("POST", "/v1/jobs", small_job(), {"Idempotency-Key": "retry-me"})
    assert first[0] == again[0] == 202 and first[2]["id"] == again[2]["id"]
    _, _, page = api.json("GET", "/v1/jobs")
    assert [j["id"] for j in page["items"]] == [first[2]["id"]]
    status, _, problem = api.json("POST", "/v1/jobs", small_job(iterations=3), {"Idempotency-Key": "retry-me"})
    assert status == 409 and problem["type"] == "/problems/idempotency-conflict"


def test_cancel_stops_a_running_job_and_keeps_its_artifacts(stack):
    api = stack.api
    stack.add_worker("w1")
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=400))
    job_id = accepted["id"]
    wait_until(lambda: (api.json("GET", f"/v1/jobs/{job_id}")[2].get("iteration") or 0) >= 1, 120, 0.2,
               what="two iterations")
    status, _, job = api.json("POST", f"/v1/jobs/{job_id}/cancel")
    assert status == 202
    job = api.wait_status(job_id, {"canceled"}, 60)
    assert 1 <= job["iteration"] < 399
    _, _, records = api.json("GET", f"/v1/jobs/{job_id}/iterations")
    assert len(records) == job["iteration"] + 1
    assert api.json("POST", f"/v1/jobs/{job_id}/cancel")[0] == 409      # already finished

    _, _, queued = api.json("POST", "/v1/jobs", small_job(iterations=400))      # cancel while queued/just started
    api.json("POST", f"/v1/jobs/{queued['id']}/cancel")
    assert api.wait_status(queued["id"], {"canceled"}, 60)["status"] == "canceled"


def test_two_workers_share_the_queue(stack):
    api = stack.api
    stack.add_worker("w1")
    stack.add_worker("w2")
    ids = [api.json("POST", "/v1/jobs", small_job(iterations=30, seed=s))[2]["id"] for s in (1, 2)]
    for job_id in ids:
        assert api.wait_status(job_id, {"succeeded", "failed"}, 240)["status"] == "succeeded"
    workers = {stack.store.get_json(f"{job_id}/record.json")["worker"] for job_id in ids}
    assert workers == {"w1", "w2"}


def test_sigkill_of_a_worker_hands_the_job_to_another_from_its_checkpoint(stack):
    api = stack.api
    first = stack.add_worker("doomed")
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=40))
    job_id = accepted["id"]
    wait_until(lambda: (api.json("GET", f"/v1/jobs/{job_id}")[2].get("iteration") or 0) >= 3, 180, 0.1,
               what="three iterations")
    first.kill(signal.SIGKILL)
    killed_at = time.monotonic()
    stack.add_worker("survivor")
    wait_until(lambda: api.json("GET", f"/v1/jobs/{job_id}")[2]["attempts"] == 2, 120, 0.1, what="the takeover")
    took_over = time.monotonic() - killed_at
    job = api.wait_status(job_id, {"succeeded", "failed"}, 300)
    assert job["status"] == "succeeded" and job["attempts"] == 2
    print(f"takeover {took_over:.1f} s after the SIGKILL (lease 3 s)")
    events = stack.store.read_events(f"{job_id}/")[0]
    resumed = [e for e in events if e["type"] == "resumed"]
    assert resumed and resumed[0]["iteration"] >= 3 and resumed[0]["attempt"].startswith("survivor")
    after = events[events.index(resumed[0]):]
    assert all(not (e.get("attempt") or "").startswith("doomed") for e in after)   # no write of the dead attempt


def test_a_job_that_keeps_killing_its_worker_fails_after_max_attempts(stack):
    api = stack.api
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=400))
    job_id = accepted["id"]
    for attempt in range(2):
        worker = stack.add_worker(f"victim{attempt}", NDRF_MAX_ATTEMPTS="2")

        def running(expected=attempt + 1):
            job = api.json("GET", f"/v1/jobs/{job_id}")[2]
            return job["attempts"] == expected and job["status"] == "running"

        wait_until(running, 120, 0.1, what="running")
        worker.kill(signal.SIGKILL)
    stack.add_worker("judge", NDRF_MAX_ATTEMPTS="2")
    job = api.wait_status(job_id, {"failed"}, 60)
    assert "crashed its worker 2 times" in job["error"]


def test_redis_restart_without_persistence_the_job_still_finishes(stack, redis_server):
    api = stack.api
    stack.add_worker("w1")
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=25))
    job_id = accepted["id"]
    wait_until(lambda: (api.json("GET", f"/v1/jobs/{job_id}")[2].get("iteration") or 0) >= 2, 120, 0.1,
               what="two iterations")
    redis_server.stop()
    time.sleep(1.0)
    redis_server.start()                     # same port, empty: the queue entry and the lease are gone
    job = api.wait_status(job_id, {"succeeded", "failed"}, 180)
    assert job["status"] == "succeeded", job

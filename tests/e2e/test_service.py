"""The service end to end: real ``ndrf serve`` (uvicorn) and ``ndrf worker`` processes against a
real Redis server started by the tests (no persistence, so it can be restarted empty).

Every case runs on a folder store; those that read and write the store in their own ways run on
an S3 bucket as well (``store_env``). The multi-worker cases on S3, where no folder is shared,
are tests/e2e/test_service_s3.py."""

from __future__ import annotations

import signal
import time

import numpy as np
import pytest

from harness.cluster import small_job, start_api, wait_until
from tests.support.service import read_sse


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
        # one name for the answer from the record to the API (#45); parameters, target: deprecated copies
        assert list(job["estimate"].values()) == records[-1]["estimate"] and job["parameters"] == job["estimate"]
        assert job["target_values"] == job["target"] and len(job["target_values"]) == 3
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


@pytest.mark.parametrize("store_env", ["folder"], indirect=True)   # S3: tests/e2e/test_service_s3.py
def test_an_auto_job_says_what_it_chose_through_the_api(tmp_path, store_env):
    """``"method": "auto"`` over HTTP: the record keeps what was asked, the plan says what ran and
    why, each decision with its reason, and the iteration records name their views."""
    proc, api = start_api(tmp_path, store_env)
    try:
        status, _, accepted = api.json("POST", "/v1/jobs", small_job("auto", iterations=2))
        assert status == 202
        events = [e["data"] for e in read_sse(api, accepted["id"], timeout=300)]
        kinds = [e["type"] for e in events]
        assert "plan" in kinds and events[-1]["status"] == "succeeded"
        _, _, job = api.json("GET", f"/v1/jobs/{accepted['id']}")
        assert job["method"] == "auto"
        recipe = job["plan"]["recipe"]
        assert job["plan"]["method"] == recipe["method"] == "prb" and recipe["optimizer"] == "levenberg-marquardt"
        assert {d["what"] for d in recipe["decisions"]} >= {"method", "optimizer", "depth"}
        assert all(d["reason"] for d in recipe["decisions"])
        assert [e["views"] for e in events if e["type"] == "iteration"] == [[0], [0]]
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


@pytest.mark.parametrize("store_env", ["folder"], indirect=True)   # S3: tests/e2e/test_service_s3.py
def test_the_dashboard_can_ask_a_running_job_for_its_images(stack):
    """``POST /v1/jobs/{id}/images`` through a real worker and its sandboxed child (SIGUSR2): the
    next iteration writes every view's render and the gradient images, off the job's schedule."""
    api = stack.api
    stack.add_worker("w1")
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=400, images_every=100000))
    job_id = accepted["id"]
    wait_until(lambda: (api.json("GET", f"/v1/jobs/{job_id}")[2].get("iteration") or 0) >= 2, 120, 0.2,
               what="three iterations")
    status, _, job = api.json("POST", f"/v1/jobs/{job_id}/images")
    assert status == 202 and job["images_requested"]
    asked_at = job["iteration"]

    def written() -> list[int]:
        _, _, records = api.json("GET", f"/v1/jobs/{job_id}/iterations")
        return [r["iteration"] for r in records if r["images"] and r["iteration"] > asked_at]

    wait_until(lambda: written(), 60, 0.2, what="an iteration with images")
    k = written()[0]
    assert k < 399                                                     # not the last iteration's own images
    assert stack.store.exists(f"{job_id}/iterations/{k:06d}/gradients.npy")
    assert not api.json("GET", f"/v1/jobs/{job_id}")[2]["images_requested"]   # answered: the request is cleared
    api.json("POST", f"/v1/jobs/{job_id}/cancel")
    api.wait_status(job_id, {"canceled"}, 60)
    assert api.json("POST", f"/v1/jobs/{job_id}/images")[0] == 409      # no next iteration


@pytest.mark.parametrize("store_env", ["folder"], indirect=True)   # S3: tests/e2e/test_service_s3.py
def test_two_workers_share_the_queue(stack):
    api = stack.api
    stack.add_worker("w1")
    stack.add_worker("w2")
    ids = [api.json("POST", "/v1/jobs", small_job(iterations=30, seed=s))[2]["id"] for s in (1, 2)]
    for job_id in ids:
        assert api.wait_status(job_id, {"succeeded", "failed"}, 240)["status"] == "succeeded"
    workers = {stack.store.get_json(f"{job_id}/record.json")["worker"] for job_id in ids}
    assert workers == {"w1", "w2"}


@pytest.mark.parametrize("store_env", ["folder"], indirect=True)   # S3: tests/e2e/test_service_s3.py
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


@pytest.mark.parametrize("store_env", ["folder"], indirect=True)   # S3: tests/e2e/test_service_s3.py
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


@pytest.mark.parametrize("store_env", ["folder"], indirect=True)   # S3: tests/e2e/test_service_s3.py
def test_redis_restart_without_persistence_the_job_still_finishes(stack, redis_server):
    api = stack.api
    stack.add_worker("w1")
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=25))
    job_id = accepted["id"]
    wait_until(lambda: (api.json("GET", f"/v1/jobs/{job_id}")[2].get("iteration") or 0) >= 2, 120, 0.1,
               what="two iterations")
    redis_server.kill()
    time.sleep(1.0)
    redis_server.start()                     # same port, empty: the queue entry and the lease are gone
    job = api.wait_status(job_id, {"succeeded", "failed"}, 180)
    assert job["status"] == "succeeded", job

"""Keys, tenancy and read tokens against a real ``ndrf serve``: every ``/v1`` route needs a key,
a key sees only its own jobs (another key's job is a 404 on every job route), an admin key sees
all, and the dashboard's short-lived read tokens open one job's GET routes and nothing else."""

from __future__ import annotations

import signal
import subprocess
import sys

import pytest

from harness.cluster import ROOT, Api, small_job, start_api

KEYS = {"NDRF_API_KEYS": "alice-key,bob-key", "NDRF_ADMIN_KEYS": "admin-key"}


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("auth")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), **KEYS})
    alice, bob, admin = (Api(api.base, key) for key in ("alice-key", "bob-key", "admin-key"))
    _, _, job = alice.json("POST", "/v1/jobs", small_job("direct", iterations=2), {"Idempotency-Key": "same"})
    alice.wait_status(job["id"], {"succeeded"}, 180)
    yield api, alice, bob, admin, job["id"]
    proc.kill(signal.SIGKILL)


def test_every_v1_route_needs_a_key(served):
    api, *_ = served
    anonymous = Api(api.base, None)
    status, headers, problem = anonymous.json("GET", "/v1/jobs")
    assert status == 401 and problem["status"] == 401 and "bearer" in headers["www-authenticate"].lower()
    assert anonymous.json("GET", "/v1/jobs", headers={"Authorization": "Bearer wrong"})[0] == 401
    assert anonymous.json("GET", "/v1/scenes")[0] == 401
    assert anonymous.json("GET", "/v1/scenes?access_token=alice-key")[0] == 401   # keys never travel in URLs
    assert anonymous.request("GET", "/healthz")[0] == 200                         # probes stay open


JOB_ROUTES = [("GET", ""), ("GET", "/iterations"), ("GET", "/events"), ("GET", "/iterations/0/render.png"),
              ("GET", "/iterations/0/silhouette.png"),
              ("GET", "/iterations/1/gradients/0.png"), ("GET", "/iterations/1/gradients.npy"),
              ("GET", "/targets/0.png"), ("GET", "/targets/0.exr"), ("GET", "/checkpoints/latest"), ("POST", "/cancel"),
              ("DELETE", "")]


@pytest.mark.parametrize("method, route", JOB_ROUTES)
def test_a_key_cannot_reach_another_keys_job(served, method, route):
    _, alice, bob, _, job_id = served
    status, _, body = bob.request(method, f"/v1/jobs/{job_id}{route}")
    assert status == 404, body                     # not 403: ids of other keys' jobs are not confirmed
    assert alice.request("GET", f"/v1/jobs/{job_id}")[0] == 200


def test_lists_and_idempotency_keys_are_per_key(served):
    _, alice, bob, admin, job_id = served
    assert [j["id"] for j in alice.json("GET", "/v1/jobs")[2]["items"]] == [job_id]
    assert bob.json("GET", "/v1/jobs")[2]["items"] == []
    assert job_id in [j["id"] for j in admin.json("GET", "/v1/jobs")[2]["items"]]
    status, _, other = bob.json("POST", "/v1/jobs", small_job("direct", iterations=2), {"Idempotency-Key": "same"})
    assert status == 202 and other["id"] != job_id    # the same Idempotency-Key, another key: another job


def test_read_tokens_open_one_jobs_get_routes_only(served):
    api, alice, bob, _, job_id = served
    token = alice.json("GET", f"/v1/jobs/{job_id}")[2]["read_token"]
    anonymous = Api(api.base, None)
    assert anonymous.request("GET", f"/v1/jobs/{job_id}/targets/0.png?token={token}")[0] == 200
    assert anonymous.request("GET", f"/v1/jobs/{job_id}/events?token={token}")[0] == 200
    for name in ("tok%65n", "%74oken"):            # only the literal name: a log or proxy matches that one
        assert anonymous.request("GET", f"/v1/jobs/{job_id}/events?{name}={token}")[0] == 401, name
    assert anonymous.request("POST", f"/v1/jobs/{job_id}/cancel?token={token}")[0] == 401     # reads only
    assert anonymous.request("GET", f"/v1/jobs?token={token}")[0] == 401                      # this job only
    other = bob.json("POST", "/v1/jobs", small_job("direct", iterations=1))[2]["id"]
    assert anonymous.request("GET", f"/v1/jobs/{other}?token={token}")[0] == 401
    forged = token[:-2] + ("AA" if not token.endswith("AA") else "BB")
    assert anonymous.request("GET", f"/v1/jobs/{job_id}?token={forged}")[0] == 401


def test_delete_is_for_the_owner_and_finished_jobs(served):
    _, alice, _, _, _ = served
    _, _, job = alice.json("POST", "/v1/jobs", small_job("direct", iterations=1))
    alice.wait_status(job["id"], {"succeeded"}, 180)
    assert alice.request("DELETE", f"/v1/jobs/{job['id']}")[0] == 204
    assert alice.request("GET", f"/v1/jobs/{job['id']}")[0] == 404


def test_serve_refuses_a_public_address_without_keys(tmp_path):
    env = {"PATH": "/usr/bin:/bin", "NDRF_STORE": str(tmp_path)}
    done = subprocess.run([sys.executable, "-m", "cli.main", "serve", "--host", "0.0.0.0", "--port", "1"],
                          cwd=ROOT, env=env, capture_output=True, text=True, timeout=60)
    assert done.returncode != 0 and "refusing to serve 0.0.0.0 without API keys" in done.stderr

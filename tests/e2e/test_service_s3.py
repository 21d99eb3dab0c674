"""Several machines, no shared disk: the API and two workers (real processes) share a Redis and a
bucket of the moto S3 server on loopback, each with a scratch folder of its own, and nothing else
on disk in common. (tests/e2e/test_service.py runs the whole service suite against both stores; this
file adds what only a bucket-shaped deployment shows.)"""

from __future__ import annotations

import io
import shutil
import signal
import urllib.error
import urllib.request

import numpy as np
import pytest

from harness.cluster import Process, Redis, small_job, start_api, wait_until
from services.jobs.isolation import KERNELS
from tests.support.service import open_test_store, read_sse

pytestmark = pytest.mark.slow


@pytest.fixture()
def machines(tmp_path, s3_server):
    redis = Redis().start()
    env = {"REDIS_URL": redis.url, "NDRF_LEASE_SECONDS": "3", "NDRF_API_KEYS": "k-one",
           **s3_server.env(prefix=f"m-{tmp_path.name}")}
    processes: list[Process] = []

    class Machines:
        def __init__(self):
            self.env = env
            self.store = open_test_store(env)
            api_proc, self.api = start_api(tmp_path, {**env, "NDRF_SCRATCH": str(tmp_path / "api-scratch"),
                                                      "NDRF_S3_PRESIGN_BYTES": "100000"})
            processes.append(api_proc)

        def worker(self, name: str) -> Process:
            scratch = tmp_path / f"{name}-scratch"
            proc = Process(["-v", "worker", "--name", name], {**env, "NDRF_SCRATCH": str(scratch)},
                           tmp_path / f"{name}.log")
            proc.scratch = scratch  # type: ignore[attr-defined]
            processes.append(proc)
            return proc

    yield Machines()
    for proc in processes:
        proc.kill(signal.SIGKILL)
    redis.kill()


def _no_redirect(api, path: str):
    """GET without following redirects: (status, Location or body)."""
    class Stop(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *args, **kwargs):
            return None

    req = urllib.request.Request(api.base + path, headers={"Authorization": f"Bearer {api.key}"})
    try:
        with urllib.request.build_opener(Stop).open(req, timeout=30) as resp:
            return resp.status, resp.read()
    except urllib.error.HTTPError as err:
        return err.code, err.headers.get("Location")


def test_api_and_two_workers_without_a_shared_folder(machines, tmp_path):
    api = machines.api
    w1, w2 = machines.worker("m1"), machines.worker("m2")
    ids = [api.json("POST", "/v1/jobs", small_job(iterations=5, seed=s))[2]["id"] for s in (1, 2)]
    for job_id in ids:
        events = read_sse(api, job_id, timeout=240)
        assert [e["data"]["type"] for e in events].count("iteration") == 5
        assert events[-1]["data"]["status"] == "succeeded"
        assert [e["id"] for e in events] == list(range(events[0]["id"], events[-1]["id"] + 1))   # no gap
    assert {machines.store.get_json(f"{j}/record.json")["worker"] for j in ids} == {"m1", "m2"}
    assert not (tmp_path / "store").exists()
    for worker in (w1, w2):   # the staged scenes are removed as the attempt ends; the keys' kernel caches stay
        wait_until(lambda w=worker: not any(p.name != KERNELS for p in w.scratch.iterdir()), 30,
                   what=f"{worker.scratch} emptied of staged scenes")

    job_id = ids[0]
    status, headers, png = api.request("GET", f"/v1/jobs/{job_id}/iterations/4/render.png")
    assert status == 200 and headers["content-type"] == "image/png" and png[:4] == b"\x89PNG"
    status, _, npy = api.request("GET", f"/v1/jobs/{job_id}/iterations/4/gradients/1.npy")   # a byte range
    assert status == 200 and np.load(io.BytesIO(npy)).shape == (16, 16, 3)
    assert api.request("GET", f"/v1/jobs/{job_id}/iterations/4/gradients/0.png")[0] == 200

    # a checkpoint (> NDRF_S3_PRESIGN_BYTES) is a redirect to a pre-signed URL of the bucket
    status, location = _no_redirect(api, f"/v1/jobs/{job_id}/checkpoints/latest")
    assert status == 307 and "X-Amz-Signature=" in location
    with urllib.request.urlopen(location, timeout=30) as resp:
        assert resp.read() == machines.store.get(f"{job_id}/checkpoints/latest.pt")


def test_sigkill_and_the_machine_gone_another_worker_resumes_from_the_bucket(machines):
    api = machines.api
    doomed = machines.worker("doomed")
    # every iteration of the 30 is checked below: stop.auto off (it tests the resume, not the stop)
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=30, stop={"auto": False}))
    job_id = accepted["id"]
    wait_until(lambda: (api.json("GET", f"/v1/jobs/{job_id}")[2].get("iteration") or 0) >= 3, 180, 0.1,
               what="three iterations")
    doomed.kill(signal.SIGKILL)
    shutil.rmtree(doomed.scratch)                 # its disk is gone with it: only the bucket remains
    machines.worker("survivor")
    job = api.wait_status(job_id, {"succeeded", "failed"}, 240)
    assert job["status"] == "succeeded" and job["attempts"] == 2
    events = machines.store.read_events(f"{job_id}/")[0]
    resumed = [e for e in events if e["type"] == "resumed"]
    assert resumed and resumed[0]["iteration"] >= 3 and resumed[0]["attempt"].startswith("survivor")
    assert all(not (e.get("attempt") or "").startswith("doomed") for e in events[events.index(resumed[0]):])
    assert [r["iteration"] for r in api.json("GET", f"/v1/jobs/{job_id}/iterations")[2]] == list(range(30))

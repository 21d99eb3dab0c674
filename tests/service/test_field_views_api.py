"""``POST /v1/jobs/{id}/views`` (``api/routes/field_views.py``): bodies out of range are 422s, a
key reaches only its own jobs' views (404 otherwise, as every job route), and a view of a trained
job renders in the sandboxed child and names each file, which can then be read."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from services.settings import Settings
from tests.support.service import small_job, wait_until

ALICE, BOB = {"Authorization": "Bearer alice-key"}, {"Authorization": "Bearer bob-key"}
CAMERA = {"origin": [0.3, 0.2, 3.0], "target": [0.0, 0.0, 0.0], "resolution": [16, 16], "spp": 2}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from api.app import create_app

    store = tmp_path_factory.mktemp("views-api") / "store"
    with TestClient(create_app(Settings(store=str(store), api_keys=["alice-key", "bob-key"]))) as client:
        yield client


@pytest.mark.parametrize("body", [
    {**CAMERA, "spp": 1000},
    {**CAMERA, "resolution": [4096, 16]},
    {**CAMERA, "prb_spp": 100_000},
    {**CAMERA, "sensor": 0},
    {"origin": [0, 0, 3]},
    {**CAMERA, "fov": 180},
    {**CAMERA, "unknown": 1},
])
def test_view_bodies_out_of_range_are_422(client, body):
    response = client.post("/v1/jobs/0123456789abcdef0123/views", json=body, headers=ALICE)
    assert response.status_code == 422, response.text


def test_views_need_a_key(client):
    assert client.post("/v1/jobs/0123456789abcdef0123/views", json=CAMERA).status_code == 401


@pytest.mark.slow  # a job and a view, each in a sandboxed child: ~30 s
def test_a_view_of_a_trained_job_names_its_files_and_only_its_owner_reaches_it(client):
    submitted = client.post("/v1/jobs", json=small_job("ndrf-lhs", iterations=2), headers=ALICE)
    assert submitted.status_code == 202, submitted.text
    job_id = submitted.json()["id"]

    def finished():
        status = client.get(f"/v1/jobs/{job_id}", headers=ALICE).json()["status"]
        return status if status in ("succeeded", "failed", "canceled") else None

    assert wait_until(finished, 600, 0.3, what="the job") == "succeeded"  # ~10 s on idle cores
    assert client.post(f"/v1/jobs/{job_id}/views", json=CAMERA, headers=BOB).status_code == 404
    response = client.post(f"/v1/jobs/{job_id}/views", json={**CAMERA, "prb_spp": 4}, headers=ALICE)
    assert response.status_code == 201, response.text
    view = response.json()
    assert {"radiance.npy", "radiance.png", "gradients.npy", "gradient-0.png", "prb.npy", "prb-2.png",
            "view.json"} <= set(view["files"])
    assert len(view["scalars"]) == 3 and view["iteration"] == 2
    got = client.get(view["files"]["gradients.npy"], headers=ALICE)
    assert got.status_code == 200
    gradients = np.load(__import__("io").BytesIO(got.content), allow_pickle=False)
    assert gradients.shape == (3, 16, 16, 3) and np.isfinite(gradients).all()
    assert client.get(view["files"]["radiance.png"], headers=BOB).status_code == 404
    assert client.get(f"/v1/jobs/{job_id}/views/{view['id']}/secret.txt", headers=ALICE).status_code == 422
    bad = client.post(f"/v1/jobs/{job_id}/views", json={**CAMERA, "up": [0.3, 0.2, 3.0]}, headers=ALICE)
    assert bad.status_code == 422 and "parallel" in bad.text

    # warm starts from this job: never for another key, never with other parameter keys
    warm = small_job("ndrf-lhs", iterations=1, warm_start={"job": job_id})
    stolen = client.post("/v1/jobs", json=warm, headers=BOB)
    assert stolen.status_code == 422 and "warm_start.job" in stolen.text and "of this API key" in stolen.text
    other = {**warm, "parameters": [{"key": "green.reflectance.value"}],
             "targets": {"synthetic": {"values": {"green.reflectance.value": [0.1, 0.5, 0.1]}, "spp": 16}}}
    refused = client.post("/v1/jobs", json=other, headers=ALICE)
    assert refused.status_code == 422 and "other parameter keys" in refused.text

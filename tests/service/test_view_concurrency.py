"""Concurrent views of one job (issue 38): every answer is a 201 (or a 409), never a 500; the
views of one checkpoint are serialized on one warm child (one child started, not one per
request); a warm child evicted while a view is in flight on it finishes that view; and another
key's view, and its warm child, are unaffected."""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor

import pytest
from fastapi.testclient import TestClient

from harness.cluster import small_job, wait_until
from services.settings import Settings

ALICE, BOB = {"Authorization": "Bearer alice-key"}, {"Authorization": "Bearer bob-key"}
CAMERA = {"origin": [0.3, 0.2, 3.0], "target": [0.0, 0.0, 0.0], "resolution": [16, 16], "spp": 1}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from api.app import create_app

    store = tmp_path_factory.mktemp("views-concurrent") / "store"
    # four places per key: the key's concurrent views reach the view children at once
    settings = Settings(store=str(store), api_keys=["alice-key", "bob-key"], admission_per_key=4,
                        preflight_workers=6, view_children=2, view_keep_seconds=900)   # none idles out
    with TestClient(create_app(settings)) as client:
        yield client


def _trained(client, headers) -> str:
    submitted = client.post("/v1/jobs", json=small_job("ndrf-lhs", iterations=1), headers=headers)
    assert submitted.status_code == 202, submitted.text
    job_id = submitted.json()["id"]

    def finished():
        status = client.get(f"/v1/jobs/{job_id}", headers=headers).json()["status"]
        return status if status in ("succeeded", "failed", "canceled") else None

    assert wait_until(finished, 600, 0.3, what="the job") == "succeeded"
    return job_id


@pytest.mark.slow  # three small jobs and four view children: ~90 s on two shared cores
def test_concurrent_views_of_one_job_are_serialized_and_never_a_500(client):
    alice_job, other_job, bob_job = _trained(client, ALICE), _trained(client, ALICE), _trained(client, BOB)

    def view(args):
        job_id, headers, index = args
        body = {**CAMERA, "origin": [0.3 - 0.1 * index, 0.2, 3.0], "inline": index % 2 == 1}
        return client.post(f"/v1/jobs/{job_id}/views", json=body, headers=headers)

    asked = [(alice_job, ALICE, i) for i in range(4)] + [(bob_job, BOB, 0)]
    with ThreadPoolExecutor(len(asked)) as pool:
        answers = list(pool.map(view, asked))
    statuses = [a.status_code for a in answers]
    assert all(s in (201, 409) for s in statuses), [a.text for a in answers]
    alice, bob = answers[:4], answers[4]
    assert bob.status_code == 201, bob.text
    assert all(a.status_code == 201 for a in alice), [a.text for a in alice]   # serialized: none refused
    # one warm child answered alice's four views (one started it), not four children at once
    assert sorted(a.json()["warm"] for a in alice) == [False, True, True, True]
    assert bob.json()["warm"] is False
    # bob's warm child survived alice's views: his next view is warm
    again = client.post(f"/v1/jobs/{bob_job}/views", json=CAMERA, headers=BOB)
    assert again.status_code == 201 and again.json()["warm"] is True, again.text

    # alice's view of her other job evicts her first job's warm child (two children here: bob's
    # and hers) while a view is in flight on it: that view still finishes, on that child
    with ThreadPoolExecutor(2) as pool:
        moved = {**CAMERA, "origin": [0.0, 0.3, 3.0], "prb_spp": 1024}   # seconds in the child
        first = pool.submit(client.post, f"/v1/jobs/{alice_job}/views", json=moved, headers=ALICE)
        time.sleep(1.0)
        second = pool.submit(client.post, f"/v1/jobs/{other_job}/views", json=CAMERA, headers=ALICE)
        first, second = first.result(), second.result()
    assert first.status_code == 201 and second.status_code == 201, (first.text, second.text)
    assert first.json()["warm"] is True and second.json()["warm"] is False
    again = client.post(f"/v1/jobs/{bob_job}/views", json=CAMERA, headers=BOB)
    assert again.status_code == 201 and again.json()["warm"] is True, again.text

"""The routes raise the services' exceptions and the app's handlers answer (``api.problems.install``):
an unknown job or experiment is a ``404``, a conflict a ``409`` whose problem type the route declares
(``conflict(slug)``). The bodies are compared byte for byte with what the routes' own try/except
blocks answered before the handlers replaced them (issue 36)."""

from __future__ import annotations

import json

import pytest
from fastapi.testclient import TestClient

from api.app import create_app
from schemas.experiments import ExperimentRecord, ExperimentStatus
from schemas.records import JobRecord, JobStatus
from services.settings import Settings

FINISHED, QUEUED, UNKNOWN = "00000000000000000001", "00000000000000000002", "0000000000000000000f"
EXPERIMENT = "e00000000000000000001"


def _problem(status: int, title: str, detail: str, slug: str, path: str) -> bytes:
    """A problem document as the API serialises it (compact JSON, this key order)."""
    return json.dumps({"type": f"/problems/{slug}", "title": title, "status": status, "detail": detail,
                       "instance": path}, separators=(",", ":")).encode()


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    settings = Settings(store=str(tmp_path_factory.mktemp("problems") / "store"))
    with TestClient(create_app(settings)) as client:
        runtime = client.app.state.runtime
        now = "2026-01-01T00:00:00.000+00:00"
        for job_id, status in ((FINISHED, JobStatus.SUCCEEDED), (QUEUED, JobStatus.QUEUED)):
            runtime.service.states.create(JobRecord(id=job_id, status=status, method="direct", scene="cornell-box",
                                                    created=now, updated=now, iterations=1))
        runtime.experiments.states.create(ExperimentRecord(id=EXPERIMENT, status=ExperimentStatus.SUCCEEDED,
                                                           created=now, updated=now, sweep={}, varied=[]), {})
        yield client


@pytest.mark.parametrize("method, path, status, title, detail, slug", [
    ("GET", f"/v1/jobs/{UNKNOWN}", 404, "Not found", f"no job '{UNKNOWN}'", "unknown-job"),
    ("POST", f"/v1/jobs/{UNKNOWN}/cancel", 404, "Not found", f"no job '{UNKNOWN}'", "unknown-job"),
    ("GET", f"/v1/jobs/{UNKNOWN}/iterations", 404, "Not found", f"no job '{UNKNOWN}'", "unknown-job"),
    ("GET", "/v1/jobs/not-an-id/events", 404, "Not found", "no job 'not-an-id'", "unknown-job"),
    ("POST", f"/v1/jobs/{FINISHED}/cancel", 409, "Conflict", f"job {FINISHED} is already succeeded", "job-finished"),
    ("POST", f"/v1/jobs/{QUEUED}/images", 409, "Conflict",
     f"job {QUEUED} is not running: it has no next iteration to write images at", "job-not-running"),
    ("DELETE", f"/v1/jobs/{QUEUED}", 409, "Conflict", f"job {QUEUED} is queued: cancel it first", "job-active"),
    ("GET", "/v1/experiments/e0000000000000000000f", 404, "Not found", "no experiment 'e0000000000000000000f'",
     "unknown-experiment"),
    ("POST", f"/v1/experiments/{EXPERIMENT}/cancel", 409, "Conflict", f"experiment {EXPERIMENT} is already succeeded",
     "experiment-finished"),
    ("POST", f"/v1/experiments/{EXPERIMENT}/retry", 409, "Conflict",
     f"experiment {EXPERIMENT} has no failed or canceled runs to retry", "nothing-to-retry"),
])
def test_service_exceptions_answer_the_problem_the_route_declares(client, method, path, status, title, detail, slug):
    answer = client.request(method, path)
    assert answer.status_code == status
    assert answer.headers["content-type"] == "application/problem+json"
    assert answer.content == _problem(status, title, detail, slug, path)


def test_openapi_names_each_409_problem_type(client):
    paths = client.get("/openapi.json").json()["paths"]
    assert paths["/v1/jobs/{job_id}/cancel"]["post"]["responses"]["409"]["x-problem-type"] == "/problems/job-finished"
    assert paths["/v1/jobs"]["post"]["responses"]["409"]["x-problem-type"] == "/problems/idempotency-conflict"

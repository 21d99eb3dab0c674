"""Schemathesis against the OpenAPI schema of a real ``ndrf serve`` process: whatever the
generated requests (valid and invalid per the schema), no response is a 5xx. The store holds
one finished job, so the artifact routes see an existing id as well as random ones.

(Schemathesis' own pytest plugin does not run under pytest 9 yet, so the operations are driven
with Hypothesis directly.)"""

from __future__ import annotations

import signal

import pytest
import schemathesis
from hypothesis import HealthCheck, given, settings

from harness.cluster import small_job, start_api


@pytest.fixture(scope="module")
def served(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("fuzz")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), "NDRF_MAX_ITERATIONS": "5",
                                "NDRF_MAX_SPP": "16", "NDRF_MAX_RESOLUTION": "32"})
    _, _, accepted = api.json("POST", "/v1/jobs", small_job("direct", iterations=2))
    api.wait_status(accepted["id"], {"succeeded"}, 120)
    yield api, accepted["id"]
    proc.kill(signal.SIGKILL)


@pytest.mark.parametrize("examples, at_least", [
    pytest.param(10, 80, id="fast"),
    pytest.param(90, 1000, id="1000-cases", marks=pytest.mark.slow),
])
def test_no_operation_answers_with_a_server_error(served, examples, at_least):
    api, job_id = served
    schema = schemathesis.openapi.from_url(f"{api.base}/openapi.json")
    operations = [result.ok() for result in schema.get_all_operations()]
    assert len(operations) >= 15
    failures, calls = [], {"n": 0}
    for operation in operations:
        @settings(max_examples=examples, deadline=None, database=None,
                  suppress_health_check=list(HealthCheck))
        @given(case=operation.as_strategy())
        def check(case):
            if "job_id" in (case.path_parameters or {}) and calls["n"] % 3 == 0:
                case.path_parameters["job_id"] = job_id          # also hit an existing job
            calls["n"] += 1
            response = case.call(timeout=30)
            if response.status_code >= 500:
                failures.append(f"{case.method} {case.formatted_path}: {response.status_code} {response.text[:300]}")

        check()
    print(f"schemathesis: {calls['n']} generated requests over {len(operations)} operations, "
          f"{len(failures)} server errors")
    assert calls["n"] >= at_least, calls
    assert not failures, "\n".join(failures[:10])

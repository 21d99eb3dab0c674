"""What only the tests need of the service in processes (the processes themselves, Redis and the
API client are :mod:`harness.cluster`): the store a service process uses, opened in the test, and
the events of a job's SSE stream."""

from __future__ import annotations

import json
import urllib.request


def open_test_store(env: dict[str, str]):
    """The store a service process started with ``env`` uses, opened in the test process."""
    from services.runtime import open_store
    from services.settings import Settings

    if env["NDRF_STORE"].startswith("s3://"):
        from services.store.s3 import S3Store

        return S3Store(env["NDRF_STORE"], endpoint=env["NDRF_S3_ENDPOINT"], access_key_id=env["AWS_ACCESS_KEY_ID"],
                       secret_access_key=env["AWS_SECRET_ACCESS_KEY"], region=env["AWS_REGION"])
    return open_store(Settings(store=env["NDRF_STORE"]))


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

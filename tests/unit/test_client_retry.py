"""The HTTP client's retries (``client/http.py``): a 429/503 with a short ``Retry-After`` is waited
out for reads and for writes with an ``Idempotency-Key``, never for other writes, and a long or
missing ``Retry-After`` is the caller's answer at once."""

from __future__ import annotations

import json
import threading
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import pytest

from client.http import ApiError, Client


class _Busy(BaseHTTPRequestHandler):
    """Answers ``refusals`` times 503 with ``retry_after``, then 200; counts the requests."""

    refusals = 1
    retry_after: str | None = "0"
    seen: list[str] = []

    def _answer(self) -> None:
        length = int(self.headers.get("Content-Length") or 0)
        self.rfile.read(length)
        type(self).seen.append(self.command)
        if len(type(self).seen) <= type(self).refusals:
            body = json.dumps({"title": "busy", "status": 503}).encode()
            self.send_response(503)
            if type(self).retry_after is not None:
                self.send_header("Retry-After", type(self).retry_after)
        else:
            body = json.dumps({"ok": True}).encode()
            self.send_response(200)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    do_GET = do_POST = _answer

    def log_message(self, *args) -> None:
        pass


@pytest.fixture
def busy():
    _Busy.seen, _Busy.refusals, _Busy.retry_after = [], 1, "0"
    server = ThreadingHTTPServer(("127.0.0.1", 0), _Busy)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    try:
        yield Client(f"http://127.0.0.1:{server.server_address[1]}", retries=2)
    finally:
        server.shutdown()
        server.server_close()


def test_a_read_is_retried_after_retry_after(busy):
    assert busy.get("/v1/jobs") == {"ok": True}
    assert _Busy.seen == ["GET", "GET"]


def test_a_write_is_retried_only_with_an_idempotency_key(busy):
    with pytest.raises(ApiError) as refused:
        busy.post("/v1/jobs", {"x": 1})
    assert refused.value.status == 503 and refused.value.headers["retry-after"] == "0"
    assert _Busy.seen == ["POST"]
    _Busy.seen = []
    assert busy.submit_job({"x": 1}, idempotency_key="k1") == {"ok": True}
    assert _Busy.seen == ["POST", "POST"]


def test_retries_run_out_and_long_or_missing_waits_are_not_waited_for(busy):
    _Busy.refusals = 10
    with pytest.raises(ApiError):
        busy.get("/v1/jobs")
    assert len(_Busy.seen) == 3                      # the first try and 2 retries
    for wait in ("3600", None, "Wed, 21 Oct 2026 07:28:00 GMT"):
        _Busy.seen, _Busy.retry_after = [], wait
        with pytest.raises(ApiError):
            busy.get("/v1/jobs")
        assert _Busy.seen == ["GET"]
    with pytest.raises(ValueError, match="retries must be >= 0"):
        Client("http://127.0.0.1:1", retries=-1)

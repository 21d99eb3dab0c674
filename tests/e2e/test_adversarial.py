"""Issue 27's availability attacks against a real ``ndrf serve`` and ``ndrf worker`` (Redis mode,
two tenant keys and an admin key). Each attack class is sent as the outside probe sent it and in
its variants; each must get its stated answer while the API's resident memory stays below idle +
300 MiB and ``/healthz`` answers within 1 s. Every attack's answer, time, peak memory above idle and
worst ``/healthz`` latency are written to ``adversarial.json`` in the test's tmp folder and logged as
a table (``pytest -o log_cli=true --log-cli-level=WARNING tests/e2e/test_adversarial.py`` shows it)."""

from __future__ import annotations

import csv
import io
import json
import signal
import socket
import threading
import time

import pytest

from harness.cluster import Api, Process, Redis, small_job, start_api
from tests.support.attack import Outcome, Watch, chunked, pieces, raw_request, report, rss_mib
from tests.support.scenes import SELF_CONTAINED_XML

pytestmark = pytest.mark.slow

KEYS = {"NDRF_API_KEYS": "alice-key,bob-key", "NDRF_ADMIN_KEYS": "admin-key"}
BUDGET_MIB = 300
HEALTHZ_SECONDS = 1.0
BODY_READ_SECONDS = 3
HEADER_READ_SECONDS = 3


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("adversarial")
    redis = Redis().start()
    env = {"REDIS_URL": redis.url, "NDRF_STORE": str(tmp / "store"), **KEYS,
           "NDRF_BODY_READ_SECONDS": str(BODY_READ_SECONDS),
           "NDRF_HEADER_READ_SECONDS": str(HEADER_READ_SECONDS), "NDRF_MAX_CONNECTIONS": "400"}
    api_proc, alice = start_api(tmp, env)
    worker = Process(["worker", "--name", "w"], env, tmp / "worker.log", nice=19)
    admin = Api(alice.base, "admin-key")
    # warm up every path the attacks take (imports, pydantic schemas), then take the idle size
    assert alice.json("POST", "/v1/jobs", {"bad": 1})[0] == 422
    status, _, job = alice.json("POST", "/v1/jobs", small_job("direct", iterations=2))
    assert status == 202, job
    alice.json("GET", f"/v1/jobs/{job['id']}")
    time.sleep(1.0)
    idle = rss_mib(api_proc.pid)
    outcomes: list[Outcome] = []
    yield {"api": alice, "admin": admin, "proc": api_proc, "tmp": tmp, "idle": idle, "job": job["id"],
           "port": int(alice.base.rsplit(":", 1)[1]), "outcomes": outcomes}
    hwm = rss_mib(api_proc.pid, "VmHWM")
    outcomes.append(Outcome("(whole suite: VmHWM)", 0, 0.0, round(hwm - idle, 1), note=f"idle {idle:.0f} MiB"))
    report(outcomes, tmp / "adversarial.json")
    for proc in (worker, api_proc):
        proc.kill(signal.SIGKILL)
    redis.kill()
    assert hwm < idle + BUDGET_MIB, f"the API peaked at {hwm:.0f} MiB, idle {idle:.0f} MiB"


def attack(stack, name: str, send, expect: int | tuple[int, ...], note: str = "") -> tuple[int, dict, bytes]:
    """Run ``send() -> (status, headers, body)`` under a :class:`Watch`; check the answer, the memory
    and /healthz; record the outcome."""
    with Watch(stack["proc"].pid, stack["api"].base, stack["idle"]) as watch:
        started = time.monotonic()
        status, headers, body = send()
        seconds = time.monotonic() - started
        time.sleep(0.3)   # what the request left behind, and a few more probes
    outcome = watch.outcome(name, status, seconds, note)
    stack["outcomes"].append(outcome)
    expected = expect if isinstance(expect, tuple) else (expect,)
    assert status in expected, (name, status, body[:500])
    assert outcome.peak_mib_above_idle < BUDGET_MIB, outcome
    assert outcome.healthz_probes >= 1 and outcome.healthz_max_seconds < HEALTHZ_SECONDS, outcome
    return status, headers, body


def post(stack, path: str, body: bytes, key: str | None = "alice-key", **headers):
    auth = {"Authorization": f"Bearer {key}"} if key else {}
    return lambda: raw_request(stack["port"], "POST", path, {"Content-Type": "application/json",
                                                             "Content-Length": str(len(body)), **auth, **headers},
                               pieces(body))


def problem(body: bytes) -> dict:
    return json.loads(body)


# ------------------------------------------------------------- 1. bodies that cost more than their size

def test_a_million_strings_in_one_list(stack):
    job = small_job()
    job["targets"]["synthetic"]["values"]["red.reflectance.value"] = ["x"] * 10**6
    _, _, body = attack(stack, "1e6 strings in one list (4 MB)", post(stack, "/v1/jobs", json.dumps(job).encode()),
                        413)
    assert "NDRF_MAX_JSON_ITEMS" in problem(body)["detail"]


def test_a_million_strings_spread_over_lists(stack):
    job = small_job()
    job["targets"]["synthetic"]["values"] = {f"k{i}": ["x"] * 9000 for i in range(111)}
    _, _, body = attack(stack, "1e6 strings in 111 lists", post(stack, "/v1/jobs", json.dumps(job).encode()), 413)
    assert "NDRF_MAX_JSON_TOKENS" in problem(body)["detail"]


def test_the_most_bad_values_within_the_limits_get_capped_errors(stack):
    job = small_job()
    job["targets"]["synthetic"]["values"] = {f"k{i}": ["x"] * 4900 for i in range(5)}   # 49k tokens
    _, _, body = attack(stack, "24.5k bad values within the limits", post(stack, "/v1/jobs", json.dumps(job).encode()),
                        422, "errors capped at 20 + a count")
    answer = problem(body)
    assert len(answer["errors"]) <= 20 and answer["more_errors"] > 10_000 and len(body) < 10_000


def test_a_million_unknown_keys(stack):
    job = small_job()
    job.update({f"unknown{i}": 1 for i in range(10**6)})
    _, _, body = attack(stack, "1e6 unknown keys (17 MB)", post(stack, "/v1/jobs", json.dumps(job).encode()), 413)
    assert "NDRF_MAX_JSON_KEYS" in problem(body)["detail"]


def test_unknown_keys_within_the_limits(stack):
    job = small_job()
    job.update({f"unknown{i}": {f"k{j}": 1 for j in range(45)} for i in range(500)})
    _, _, body = attack(stack, "500 unknown keys x 45 nested", post(stack, "/v1/jobs", json.dumps(job).encode()),
                        422, "errors capped at 20 + a count")
    answer = problem(body)
    assert len(answer["errors"]) == 20 and answer["more_errors"] == 480


@pytest.mark.parametrize("depth", [10**6, 40])
def test_deep_nesting(stack, depth):
    body = ("[" * depth + "]" * depth).encode()
    _, _, answer = attack(stack, f"nesting depth {depth}", post(stack, "/v1/jobs", body), 413)
    assert "NDRF_MAX_JSON_DEPTH" in problem(answer)["detail"]


def test_a_body_of_many_small_values_near_the_cap(stack):
    body = b"[" + b"0," * (30 << 20) + b"0]"    # 60 MiB of numbers
    _, _, answer = attack(stack, "60 MiB of numbers with a key", post(stack, "/v1/jobs", body), 413)
    assert "NDRF_MAX_JSON" in problem(answer)["detail"]


def test_concurrent_large_bodies_share_the_memory_budget(stack):
    body = b"[" + b"0," * (25 << 20) + b"0]"    # 50 MiB each, 6 at once
    answers: list[int] = []

    def one():
        try:
            answers.append(post(stack, "/v1/jobs", body)()[0])
        except OSError:   # refused before the client finished sending
            answers.append(503)

    def send():
        threads = [threading.Thread(target=one) for _ in range(6)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(60)
        return (503 if 503 in answers else 0), {}, b""

    attack(stack, "6 x 50 MiB bodies at once", send, 503, "413 / 503 + Retry-After (NDRF_MAX_BODY_MEMORY_BYTES)")
    assert len(answers) == 6 and set(answers) <= {413, 503} and 413 in answers, answers


# ------------------------------------------------------------- 2. bodies before authentication

@pytest.mark.parametrize("key", [None, "wrong-key"])
def test_no_key_50_mb_is_refused_before_the_body_is_read(stack, key):
    body = b"{" + b",".join(b'"k%d":1' % i for i in range(4 * 10**6)) + b"}"   # 51 MB, 4e6 keys
    started = time.monotonic()
    attack(stack, f"50 MB body, key {key}", post(stack, "/v1/jobs", body, key), 401)
    assert time.monotonic() - started < 1.0


def test_no_key_chunked_body(stack):
    send = lambda: raw_request(stack["port"], "POST", "/v1/experiments",
                               {"Transfer-Encoding": "chunked", "Content-Type": "application/json"}, chunked(50 << 20))
    attack(stack, "50 MB chunked body, no key", send, 401)


# ------------------------------------------------------------- the body cap

def test_a_chunked_body_over_the_cap_is_a_413(stack):
    send = lambda: raw_request(stack["port"], "POST", "/v1/jobs",
                               {"Authorization": "Bearer alice-key", "Transfer-Encoding": "chunked",
                                "Content-Type": "application/json"}, chunked(70 << 20))
    _, _, body = attack(stack, "70 MiB chunked body with a key", send, 413)
    assert "NDRF_MAX_UPLOAD_BYTES" in problem(body)["detail"]


def test_a_declared_body_over_the_cap_is_a_413_before_reading(stack):
    send = lambda: raw_request(stack["port"], "POST", "/v1/jobs",
                               {"Authorization": "Bearer alice-key", "Content-Length": str(1 << 30)}, [b"{" * 1024])
    attack(stack, "Content-Length 1 GiB", send, 413)


# ------------------------------------------------------------- 5. tokens

def test_a_token_never_renews_itself_and_stays_out_of_the_log(stack):
    api, job_id = stack["api"], stack["job"]
    _, _, job = api.json("GET", f"/v1/jobs/{job_id}")
    token = job["read_token"]
    assert token
    anonymous = Api(api.base, None)
    _, _, body = attack(stack, "GET job with ?token=", lambda: anonymous.request("GET", f"/v1/jobs/{job_id}?token={token}"),
                        200, "read_token null")
    assert json.loads(body)["read_token"] is None
    assert anonymous.request("GET", f"/v1/jobs/{job_id}/iterations?token={token}")[0] == 200
    expired = token.split(".")[0] + ".1." + token.split(".")[2]
    assert anonymous.request("GET", f"/v1/jobs/{job_id}?token={expired}")[0] == 401
    time.sleep(0.5)
    logged = stack["proc"].log.read_text(errors="replace")
    assert "token=REDACTED" in logged and token.split(".")[2] not in logged


# ------------------------------------------------------------- 8. /metrics

def test_metrics_need_an_admin_key(stack):
    api = stack["api"]
    attack(stack, "/metrics without a key", lambda: Api(api.base, None).request("GET", "/metrics"), 401)
    assert api.request("GET", "/metrics")[0] == 403
    assert stack["admin"].request("GET", "/metrics")[0] == 200


# ------------------------------------------------------------- 7. slow clients

def test_slow_bodies_are_cut_after_the_read_timeout(stack):
    port, results = stack["port"], []

    def slow_body():
        results.append(raw_request(port, "POST", "/v1/jobs", {"Authorization": "Bearer alice-key",
                                                              "Content-Length": str(1 << 20)}, [b'{"name": '],
                                   timeout=30)[0])

    def send():
        threads = [threading.Thread(target=slow_body) for _ in range(50)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
        return (results[0] if len(set(results)) == 1 else 0), {}, b""

    started = time.monotonic()
    attack(stack, "50 slow bodies (408 after 3 s)", send, 408, f"NDRF_BODY_READ_SECONDS={BODY_READ_SECONDS}")
    assert len(results) == 50 and time.monotonic() - started < BODY_READ_SECONDS + 5


def test_slow_headers_are_cut_after_the_header_timeout(stack):
    """150 connections that trickle a header line every second (slowloris) are closed by the server
    NDRF_HEADER_READ_SECONDS after they opened (api.server); the API answers meanwhile."""
    sockets: list[socket.socket] = []

    def closed(sock: socket.socket) -> bool:
        try:
            sock.sendall(b"X-Slow: 1\r\n")
            sock.settimeout(0.05)
            return sock.recv(1) == b""
        except (ConnectionError, BrokenPipeError):
            return True
        except TimeoutError:
            return False

    def send():
        for _ in range(150):
            sock = socket.create_connection(("127.0.0.1", stack["port"]))
            sock.sendall(b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\n")
            sockets.append(sock)
        started = time.monotonic()
        while time.monotonic() - started < HEADER_READ_SECONDS + 3:
            time.sleep(1.0)
            shut = sum(closed(sock) for sock in sockets)
            if shut == len(sockets):
                break
        for sock in sockets:
            sock.close()
        return (200 if shut == len(sockets) else 0), {}, f"{shut} closed".encode()

    _, _, body = attack(stack, "150 slowloris header streams", send, 200,
                        f"all closed (NDRF_HEADER_READ_SECONDS={HEADER_READ_SECONDS})")


def test_a_huge_header_is_refused(stack):
    def send():
        try:
            return raw_request(stack["port"], "GET", "/v1/jobs", {"Authorization": "Bearer alice-key",
                                                                  "X-Big": "a" * (200 << 10)})
        except ConnectionResetError:   # uvicorn answered 400 and closed while the header was still coming
            return 0, {}, b""

    attack(stack, "200 KiB header", send, (400, 0), "400, or reset before the client read it")


# ------------------------------------------------------------- 10. smaller items

def test_no_redirect_to_the_host_header(stack):
    send = lambda: raw_request(stack["port"], "GET", "/v1/jobs/", {"Host": "evil.example",
                                                                   "Authorization": "Bearer alice-key"})
    _, headers, _ = attack(stack, "trailing slash, Host evil.example", send, 404)
    assert "location" not in headers


def test_security_headers(stack):
    _, headers, _ = attack(stack, "dashboard headers", lambda: raw_request(stack["port"], "GET", "/", {}), 200)
    assert "frame-ancestors 'none'" in headers["content-security-policy"]
    assert headers["x-frame-options"] == "DENY" and headers["x-content-type-options"] == "nosniff"
    _, api_headers, _ = stack["api"].request("GET", "/v1/jobs")
    csp = {k.lower(): v for k, v in api_headers.items()}["content-security-policy"]
    assert csp.startswith("default-src 'none'")


def test_scene_errors_show_no_internal_paths(stack):
    xml = SELF_CONTAINED_XML.replace("</scene>", '<bsdf type="nosuchplugin" id="q"/></scene>')
    body = json.dumps({"xml": xml, "files": {}}).encode()
    _, _, answer = attack(stack, "scene error text", post(stack, "/v1/scenes/parameters", body), 422)
    detail = problem(answer)["detail"]
    assert "nosuchplugin" in detail and "/tmp" not in detail and ".cpp" not in detail


# ------------------------------------------------------------- 6. results.csv

def test_results_csv_cells_cannot_be_formulas(stack):
    hostile = ["=1+2", "+cmd|' /C calc'!A0", "@SUM(1,2)", "-2+3"]
    api = stack["api"]
    status, _, accepted = api.json("POST", "/v1/experiments", {
        "name": "=HYPERLINK(\"http://evil.example\")", "base": small_job("direct", iterations=2),
        "grid": {"name": hostile}, "max_concurrent": 1})
    assert status == 202, accepted
    _, _, raw = attack(stack, "results.csv with formulas",
                       lambda: api.request("GET", f"/v1/experiments/{accepted['id']}/results.csv"), 200)
    table = list(csv.reader(io.StringIO(raw.decode())))
    names = [row[table[0].index("name")] for row in table[1:]]
    assert names == ["'" + text for text in hostile]
    assert not any(cell.startswith(("=", "+", "@", "\t", "\r")) for row in table for cell in row)
    # an experiment's read token does not renew itself either
    token = api.json("GET", f"/v1/experiments/{accepted['id']}")[2]["read_token"]
    _, _, seen = Api(api.base, None).json("GET", f"/v1/experiments/{accepted['id']}?token={token}")
    assert token and seen["read_token"] is None

"""Issue 38's attacks of one tenant key ("alice") on another ("bob") with valid requests only,
against a real ``ndrf serve`` and ``ndrf worker`` (Redis mode). Each case records, like
tests/e2e/test_adversarial.py, what bob saw, the API's peak resident memory above idle and the
worst ``/healthz`` latency; the table is logged and written to ``tenants.json`` in the test's tmp
folder (``pytest -o log_cli=true --log-cli-level=WARNING tests/e2e/test_adversarial_tenants.py``).

The worker starts only for the scheduling case: the cases before it count queued jobs."""

from __future__ import annotations

import base64
import json
import signal
import statistics
import threading
import time

import pytest

from harness.cluster import Api, Process, Redis, small_job, start_api, wait_until
from tests.support.attack import Outcome, Watch, report, rss_mib
from tests.support.payloads import exr_header

pytestmark = pytest.mark.slow

KEYS = {"NDRF_API_KEYS": "alice-key,bob-key,carol-key", "NDRF_ADMIN_KEYS": "admin-key"}
ACTIVE_CAP = 3
HEALTHZ_SECONDS = 1.0


@pytest.fixture(scope="module")
def stack(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("tenants")
    redis = Redis().start()
    env = {"REDIS_URL": redis.url, "NDRF_STORE": str(tmp / "store"), **KEYS,
           "NDRF_MAX_ACTIVE_JOBS_PER_KEY": str(ACTIVE_CAP)}
    api_proc, alice = start_api(tmp, env)
    keys = {name: Api(alice.base, f"{name}-key") for name in ("alice", "bob", "carol", "admin")}
    assert keys["bob"].json("POST", "/v1/jobs", {"bad": 1})[0] == 422        # warm the paths
    time.sleep(0.5)
    idle = rss_mib(api_proc.pid)
    outcomes: list[Outcome] = []
    state = {"api": keys, "proc": api_proc, "env": env, "tmp": tmp, "idle": idle, "outcomes": outcomes,
             "worker": None}
    yield state
    report(outcomes, tmp / "tenants.json")
    for proc in (state["worker"], api_proc):
        if proc is not None:
            proc.kill(signal.SIGKILL)
    redis.kill()


def record(stack, watch: Watch, name: str, status: int, seconds: float, note: str, **extra) -> Outcome:
    outcome = watch.outcome(name, status, seconds, note, **extra)
    stack["outcomes"].append(outcome)
    assert outcome.healthz_probes >= 1 and outcome.healthz_max_seconds < HEALTHZ_SECONDS, outcome
    return outcome


def cancel_all(api: Api) -> None:
    _, _, page = api.json("GET", "/v1/jobs?limit=200")
    for job in page["items"]:
        if job["status"] in ("queued", "running"):
            api.json("POST", f"/v1/jobs/{job['id']}/cancel")


def test_concurrent_submissions_never_pass_the_active_cap(stack):
    """48 concurrent submissions against 32 made 33 active jobs: counted and taken in two steps
    (tests/service/test_tenancy.py shows the race itself failing on the old code: 48 of 48)."""
    carol = stack["api"]["carol"]
    answers: list[int] = []
    job = small_job("direct", iterations=2)

    def one(i: int) -> None:
        answers.append(carol.json("POST", "/v1/jobs", {**job, "seed": i}, timeout=300)[0])

    with Watch(stack["proc"].pid, carol.base, stack["idle"]) as watch:
        started = time.monotonic()
        threads = [threading.Thread(target=one, args=(i,)) for i in range(3 * ACTIVE_CAP)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(300)
        seconds = time.monotonic() - started
    _, _, page = carol.json("GET", "/v1/jobs?limit=200")
    active = sum(1 for j in page["items"] if j["status"] in ("queued", "running"))
    record(stack, watch, f"{3 * ACTIVE_CAP} concurrent submits, cap {ACTIVE_CAP}", 202, seconds,
           f"{active} active, answers {sorted(answers)}")
    cancel_all(carol)
    assert active == ACTIVE_CAP and sorted(answers) == [202] * ACTIVE_CAP + [429] * (2 * ACTIVE_CAP), answers


def test_an_exr_declaring_700_channels_is_refused_from_its_header(stack):
    """A 5.7 MB EXR declaring 700 channels (5.5 GiB decoded): the preflight children took 12.5 GB
    for 34 s before each 422 (pixels were counted, channels were not)."""
    alice = stack["api"]["alice"]
    exr = exr_header(1400, 1400, [f"c{i}" for i in range(700)])
    job = {**small_job("direct"), "targets": {"images": [{"sensor": 0, "data": base64.b64encode(exr).decode()}]}}
    with Watch(stack["proc"].pid, alice.base, stack["idle"]) as watch:
        started = time.monotonic()
        status, _, problem = alice.json("POST", "/v1/jobs", job)
        seconds = time.monotonic() - started
        time.sleep(0.3)
    record(stack, watch, "EXR header of 700 channels", status, seconds, "422 before any decoder")
    assert status == 422 and "NDRF_MAX_IMAGE_VALUES" in problem["detail"], problem
    assert seconds < 1.0


def _bob_submit_seconds(bob: Api, seed: int) -> float:
    started = time.monotonic()
    status, _, body = bob.json("POST", "/v1/jobs", small_job("direct", iterations=2, seed=seed), timeout=600)
    assert status == 202, body
    return time.monotonic() - started


def test_a_keys_submit_does_not_queue_behind_another_keys_experiment_checks(stack):
    """One experiment per distinct render setting held the API's shared scene checks: bob's plain
    submit took 75 s (40 settings) against 2.1 s alone."""
    alice, bob = stack["api"]["alice"], stack["api"]["bob"]
    idle = statistics.median(_bob_submit_seconds(bob, seed) for seed in range(3))
    cancel_all(bob)
    experiment = {"base": small_job("direct", iterations=2), "grid": {"render.spp": list(range(1, 13))},
                  "max_concurrent": 1}
    answers: list[int] = []
    attackers = [threading.Thread(target=lambda: answers.append(
        alice.json("POST", "/v1/experiments", experiment, timeout=600)[0])) for _ in range(2)]
    with Watch(stack["proc"].pid, bob.base, stack["idle"]) as watch:
        for thread in attackers:
            thread.start()
        time.sleep(1.0)                                  # alice's checks hold the admission slots
        seconds = _bob_submit_seconds(bob, 10)
        for thread in attackers:
            thread.join(600)
    record(stack, watch, "2 experiments x 12 render settings", 202, seconds,
           f"bob's submit {seconds:.1f} s, idle {idle:.1f} s", idle_seconds=round(idle, 3))
    cancel_all(bob)
    _, _, page = alice.json("GET", "/v1/experiments")
    for exp in page["items"]:
        alice.json("POST", f"/v1/experiments/{exp['id']}/cancel")
    cancel_all(alice)
    assert answers == [202, 202]
    assert seconds < 2 * idle, (seconds, idle)


def test_a_keys_small_job_waits_for_one_job_of_another_key_not_its_queue(stack):
    """A few heavy jobs queued first: bob's small job waited behind all of them (one FIFO)."""
    alice, bob, admin = stack["api"]["alice"], stack["api"]["bob"], stack["api"]["admin"]
    wait_until(lambda: all(j["status"] not in ("queued", "running")
                           for j in admin.json("GET", "/v1/jobs?limit=200")[2]["items"]), 120, 0.5,
               what="earlier jobs canceled")
    # stop.auto off: a job that stopped itself early would not be heavy (it did, after the earlier cases)
    heavy = [alice.json("POST", "/v1/jobs", small_job("direct", iterations=150, seed=i, stop={"auto": False}))[2]["id"]
             for i in range(3)]
    stack["worker"] = Process(["-v", "worker", "--name", "w"], stack["env"], stack["tmp"] / "worker.log")
    alice.wait_status(heavy[0], ("running",), 120)
    with Watch(stack["proc"].pid, bob.base, stack["idle"]) as watch:
        started = time.monotonic()
        status, _, small = bob.json("POST", "/v1/jobs", small_job("direct", iterations=2, seed=99))
        assert status == 202, small
        assert alice.json("GET", f"/v1/jobs/{heavy[0]}")[2]["status"] == "running"   # still the first one
        bob.wait_status(small["id"], ("succeeded",), 600)
        seconds = time.monotonic() - started
    records = {job_id: json.loads((stack["tmp"] / "store" / job_id / "record.json").read_text())
               for job_id in [*heavy, small["id"]]}
    bob_started = records[small["id"]]["started"]
    before = [job_id for job_id in heavy if (records[job_id].get("started") or "~") < bob_started]
    record(stack, watch, "bob's job behind 3 heavy jobs of alice", status, seconds,
           f"{len(before)} of alice's jobs started before it (1 worker)")
    cancel_all(alice)
    assert before == heavy[:1], (before, heavy)


def test_a_keys_stored_bytes_stop_at_its_quota_and_usage_shows_them(tmp_path):
    """Two jobs with images every iteration grew the store by 4.2 GB in 346 s: nothing bounded a
    key's total. A stack of its own with NDRF_MAX_KEY_BYTES = 2 MiB."""
    redis = Redis().start()
    env = {"REDIS_URL": redis.url, "NDRF_STORE": str(tmp_path / "store"), **KEYS, "NDRF_MAX_KEY_BYTES": str(2 << 20)}
    api_proc, alice = start_api(tmp_path, env)
    worker = Process(["-v", "worker", "--name", "w"], env, tmp_path / "worker.log")
    try:
        job = small_job("direct", iterations=300, images_every=1,
                        render={"spp": 4, "gradient_spp": 4, "resolution": [64, 64]})
        status, _, first = alice.json("POST", "/v1/jobs", job)
        assert status == 202, first
        failed = alice.wait_status(first["id"], ("failed", "succeeded"), 600)
        assert failed["status"] == "failed" and "NDRF_MAX_KEY_BYTES" in failed["error"], failed
        stored = sum(p.stat().st_size for p in (tmp_path / "store" / first["id"]).rglob("*") if p.is_file())
        assert stored <= 2 << 20, stored
        status, _, usage = alice.json("GET", "/v1/usage")
        assert status == 200 and usage["stored_bytes"]["limit"] == 2 << 20, usage
        assert usage["stored_bytes"]["used"] == stored and usage["active_jobs"]["used"] == 0
        bob = Api(alice.base, "bob-key")
        assert bob.json("POST", "/v1/jobs", small_job("direct", iterations=2))[0] == 202
    finally:
        worker.kill()
        api_proc.kill()
        redis.kill()

"""Load benchmark: status polls, job lists and SSE streams from many clients against ``ndrf serve``
(Redis mode) while 2 workers train.

    python -m bench.load                    # the full run (about 4 minutes)
    python -m bench.load --quick            # shorter phases

Phases, each against the same API while two long jobs train:

* ``submit``: submissions (``POST /v1/jobs``, preflight included) one after another, with no event
  stream open, then with ``--streams`` (200) clients streaming the training jobs' events;
* ``poll``: ``--clients`` (100) clients, each polling a job's status every ``--think`` seconds and
  listing jobs every fifth request; p50/p99 latency and requests/s;
* ``sse``: ``--sse`` (100) streams open on the training jobs; for every iteration event, the delay
  from the event's ``time`` (stamped when the worker appended it to the store, right after the
  iteration's record was written) to its arrival at the client.

CPU placement (2 cores here): the API on core 0 (``taskset -c 0``), this load generator on core 1,
the workers (and their jobs) on both cores at ``nice 19``, so the training soaks up idle time
without taking it from the API or the clients (the nice given to their sessions' autogroups too:
:class:`harness.cluster.Process`). ``--api-processes N`` serves with
``ndrf serve --workers N`` (uvicorn processes on one port; the store and Redis are shared).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import logging
import os
import shutil
import statistics
import tempfile
import time
from datetime import datetime
from pathlib import Path

import httpx

from harness.cluster import Redis, small_job, start_api, start_worker, wait_until

log = logging.getLogger("bench.load")


def percentiles(values: list[float]) -> dict:
    if not values:
        return {"n": 0}
    ordered = sorted(values)

    def at(q: float) -> float:
        return ordered[min(len(ordered) - 1, int(round(q * (len(ordered) - 1))))]

    return {"n": len(values), "p50_ms": round(at(0.5) * 1000, 1), "p99_ms": round(at(0.99) * 1000, 1),
            "max_ms": round(ordered[-1] * 1000, 1), "mean_ms": round(statistics.fmean(values) * 1000, 1)}


class Load:
    def __init__(self, base: str, training: list[str], store: Path):
        self.base, self.training, self.store = base, training, store
        self.stop = asyncio.Event()

    def client(self, n: int) -> httpx.AsyncClient:
        return httpx.AsyncClient(base_url=self.base, timeout=httpx.Timeout(120.0),
                                 limits=httpx.Limits(max_connections=n, max_keepalive_connections=n))

    # ------------------------------------------------------------ streams

    def last_seq(self, job_id: str) -> int:
        """The job's newest event in the store (same machine): streams start after it, so every
        event they receive is a live delivery, not a replay."""
        try:
            lines = (self.store / job_id / "events.jsonl").read_bytes().rstrip(b"\n").splitlines()
            return int(json.loads(lines[-1])["seq"]) if lines else 0
        except (OSError, ValueError, KeyError):
            return 0

    async def stream(self, http: httpx.AsyncClient, job_id: str, delays: list[tuple], opened: list[int]) -> None:
        """One SSE client: records ``(job, seq, written, received)`` for every iteration event written
        while it is connected (``written`` is the event's ``time``, stamped by the worker). Events
        written before the response started are the replay of what it missed while connecting
        (``Last-Event-ID``), not live delivery: not counted."""
        try:
            after = str(self.last_seq(job_id))
            async with http.stream("GET", f"/v1/jobs/{job_id}/events", headers={"Last-Event-ID": after}) as resp:
                resp.raise_for_status()
                connected = time.time()
                opened.append(1)
                async for line in resp.aiter_lines():
                    if self.stop.is_set():
                        return
                    if not line.startswith("data: "):
                        continue
                    event = json.loads(line[6:])
                    received = time.time()
                    written = datetime.fromisoformat(event["time"]).timestamp() if "time" in event else 0.0
                    if event.get("type") == "iteration" and written >= connected:
                        delays.append((job_id, int(event["seq"]), written, received))
        except (httpx.HTTPError, asyncio.CancelledError):
            return

    async def open_streams(self, n: int, delays: list[tuple]) -> tuple[list[asyncio.Task], httpx.AsyncClient]:
        http = self.client(n + 10)
        opened: list[int] = []
        tasks = [asyncio.create_task(self.stream(http, self.training[i % len(self.training)], delays, opened))
                 for i in range(n)]
        deadline = time.monotonic() + 120
        while len(opened) < n and time.monotonic() < deadline:
            await asyncio.sleep(0.2)
        log.info("%d/%d streams open", len(opened), n)
        return tasks, http

    # ------------------------------------------------------------- polls

    async def poller(self, http: httpx.AsyncClient, i: int, clients: int, think: float, polls: list[float],
                     lists: list[float], errors: list[int]) -> None:
        job_id = self.training[i % len(self.training)]
        await asyncio.sleep(max(think, 0.5) * i / clients)     # spread the starts over one period
        n = 0
        while not self.stop.is_set():
            n += 1
            listing = n % 5 == 0
            started = time.perf_counter()
            try:
                resp = await http.get("/v1/jobs?limit=20" if listing else f"/v1/jobs/{job_id}")
                ok = resp.status_code == 200
            except httpx.HTTPError:
                ok = False
            took = time.perf_counter() - started
            if not ok:
                errors.append(1)
            (lists if listing else polls).append(took)
            await asyncio.sleep(max(0.0, think - took))

    async def polls(self, clients: int, think: float, seconds: float) -> dict:
        http = self.client(clients + 10)
        polls: list[float] = []
        lists: list[float] = []
        errors: list[int] = []
        self.stop.clear()
        tasks = [asyncio.create_task(self.poller(http, i, clients, think, polls, lists, errors)) for i in range(clients)]
        started = time.perf_counter()
        await asyncio.sleep(seconds)
        self.stop.set()
        await asyncio.gather(*tasks, return_exceptions=True)
        elapsed = time.perf_counter() - started
        await http.aclose()
        return {"clients": clients, "think_seconds": think, "seconds": round(elapsed, 1),
                "requests_per_second": round((len(polls) + len(lists)) / elapsed, 1), "errors": len(errors),
                "status_poll": percentiles(polls), "job_list": percentiles(lists)}

    # ----------------------------------------------------------- submits

    async def submits(self, n: int) -> list[float]:
        out = []
        async with self.client(4) as http:
            for i in range(n):
                started = time.perf_counter()
                resp = await http.post("/v1/jobs", json=small_job(iterations=2, seed=1000 + i, name="load submit"))
                out.append(time.perf_counter() - started)
                if resp.status_code != 202:
                    raise RuntimeError(f"submission refused: {resp.status_code} {resp.text}")
                await http.post(f"/v1/jobs/{resp.json()['id']}/cancel")       # keep the workers on the training
        return out


async def scenario(base: str, training: list[str], store: Path, redis_url: str, args) -> dict:
    load = Load(base, training, store)
    report: dict = {}
    # submissions without streams, with polls going on (a light background)
    log.info("phase: submit, no streams")
    report["submit_no_streams"] = percentiles(await load.submits(args.submits))
    log.info("phase: submit, %d streams", args.streams)
    delays: list[tuple] = []
    tasks, http = await load.open_streams(args.streams, delays)
    report["streams_open"] = sum(not t.done() for t in tasks)
    report["submit_with_streams"] = percentiles(await load.submits(args.submits))
    report["poll_with_streams"] = await load.polls(args.clients, args.think, args.seconds / 2)
    load.stop.set()
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await http.aclose()
    load.stop.clear()

    log.info("phase: %d pollers", args.clients)
    report["poll"] = await load.polls(args.clients, args.think, args.seconds)
    log.info("phase: %d pollers, no think time (capacity)", args.clients)
    report["poll_saturated"] = await load.polls(args.clients, 0.0, args.seconds / 2)

    log.info("phase: %d SSE streams", args.sse)
    load.stop.clear()
    delays = []
    tasks, http = await load.open_streams(args.sse, delays)
    await asyncio.sleep(args.seconds)
    load.stop.set()
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    await http.aclose()
    report["sse"] = {"streams": args.sse, **delivery(delays, redis_url)}
    return report


def delivery(delays: list[tuple], redis_url: str) -> dict:
    """Delivery delays, whole and split where the event was published on the bus: the id Redis gave
    the ``XADD`` is its clock at that moment (same machine), so ``written -> published`` is the
    worker's share (its store write, fsync and scheduling) and ``published -> received`` the API's
    (bus wake-up, store read, fan-out) and the client's."""
    import redis

    from services.queue.redis_queue import EVENTS

    client = redis.Redis.from_url(redis_url)
    published: dict[tuple[str, int], float] = {}
    for job_id in {d[0] for d in delays}:
        for entry_id, fields in client.xrange(EVENTS.format(job_id)):
            published[(job_id, int(fields[b"seq"]))] = int(entry_id.split(b"-")[0]) / 1000
    split = [(published[(j, q)] - w, r - published[(j, q)]) for j, q, w, r in delays if (j, q) in published]
    return {"iteration_delivery": percentiles([r - w for _, _, w, r in delays]),
            "written_to_published": percentiles([a for a, _ in split]),
            "published_to_received": percentiles([b for _, b in split])}


def run(args) -> dict:
    folder = Path(tempfile.mkdtemp(prefix="ndrf-load-"))
    redis = Redis().start()
    env = {"REDIS_URL": redis.url, "NDRF_STORE": str(folder / "store"), "NDRF_SCRATCH": str(folder / "scratch"),
           "NDRF_MAX_STREAMS_PER_KEY": str(max(args.streams, args.sse) + 50),
           "NDRF_MAX_ACTIVE_JOBS_PER_KEY": "1000"}
    api_cmd = ["taskset", "-c", args.api_cpus] if args.api_cpus and shutil.which("taskset") else []
    serve_args = ["--workers", str(args.api_processes)] if args.api_processes > 1 else []
    processes = []
    try:
        api_proc, api = start_api(folder, env, prefix=api_cmd, extra=serve_args)
        processes.append(api_proc)
        processes += [start_worker(folder, env, f"trainer{i}", nice=19) for i in range(2)]
        training = []
        for i in range(2):
            status, _, body = api.json("POST", "/v1/jobs", small_job(iterations=2000, seed=i + 1, images_every=50,
                                                                     name="load training"))
            assert status == 202, body
            training.append(body["id"])

        def both_training() -> bool:
            return all((api.json("GET", f"/v1/jobs/{j}")[2] or {}).get("iteration") is not None for j in training)

        wait_until(both_training, 300, 1.0, what="both jobs training")
        if args.generator_cpus and hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, {int(c) for c in args.generator_cpus.split(",")})
        started = time.time()

        def iterations() -> list:
            return [(api.json("GET", f"/v1/jobs/{j}")[2] or {}).get("iteration") for j in training]

        before = iterations()
        report = asyncio.run(scenario(api.base, training, folder / "store", redis.url, args))
        report["training_iterations"] = {"before": before, "after": iterations()}
        report["setup"] = {"api_processes": args.api_processes, "api_cpus": args.api_cpus,
                           "generator_cpus": args.generator_cpus, "workers": "2 x nice 19, any cpu",
                           "load_average_before": os.getloadavg(), "seconds": round(time.time() - started)}
        return report
    finally:
        for proc in processes:
            proc.kill()
        redis.kill()
        shutil.rmtree(folder, ignore_errors=True)


def markdown(report: dict) -> str:
    s = report["setup"]
    lines = [f"### Load: {s['api_processes']} API process(es) on cpu {s['api_cpus']}, generator on cpu "
             f"{s['generator_cpus']}, {s['workers']} (load average before: "
             f"{', '.join(f'{x:.1f}' for x in s['load_average_before'])})", "",
             "| what | n | p50 ms | p99 ms | max ms | req/s |", "|---|---|---|---|---|---|"]

    def row(name: str, p: dict, rps: float | str = "") -> None:
        lines.append(f"| {name} | {p.get('n')} | {p.get('p50_ms')} | {p.get('p99_ms')} | {p.get('max_ms')} | {rps} |")

    row("submission, no streams", report["submit_no_streams"])
    row(f"submission, {report['streams_open']} streams open", report["submit_with_streams"])
    for key, label in (("poll_with_streams", "with the streams open"), ("poll", ""),
                       ("poll_saturated", "no think time")):
        p = report[key]
        row(f"status poll, {p['clients']} clients {label} (think {p['think_seconds']} s)", p["status_poll"],
            p["requests_per_second"])
        row(f"job list, same clients {label}", p["job_list"])
    sse = report["sse"]
    row(f"SSE iteration delivery, {sse['streams']} streams: record written -> event received", sse["iteration_delivery"])
    if "written_to_published" in sse:
        row("of which: written -> published on the bus (worker)", sse["written_to_published"])
        row("of which: published -> received (API, client)", sse["published_to_received"])
    trained = report.get("training_iterations", {})
    if trained.get("before") and trained.get("after"):
        done = sum(a - b for a, b in zip(trained["after"], trained["before"], strict=True))
        lines.append(f"\nMeanwhile the two training jobs ran {done} iterations in {s['seconds']} s "
                     f"({done / max(s['seconds'], 1):.2f} per second).")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="Shorter phases (20 s), 3 submissions each.")
    parser.add_argument("--clients", type=int, default=100)
    parser.add_argument("--think", type=float, default=1.0, help="Seconds between a client's polls.")
    parser.add_argument("--streams", type=int, default=200, help="Streams open during the submission phase.")
    parser.add_argument("--sse", type=int, default=100, help="Streams of the delivery phase.")
    parser.add_argument("--submits", type=int, default=6)
    parser.add_argument("--seconds", type=float, default=60.0)
    parser.add_argument("--api-processes", type=int, default=1)
    parser.add_argument("--api-cpus", default="0", help="taskset list for the API ('' = any cpu).")
    parser.add_argument("--generator-cpus", default="1", help="cpus of this generator ('' = any cpu).")
    parser.add_argument("--out", default="bench/results/load")
    args = parser.parse_args(argv)
    if args.quick:
        args.seconds, args.submits = 20.0, 3
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    logging.getLogger("httpx").setLevel(logging.WARNING)      # one line per request would cost the generator
    report = run(args)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(report))
    log.info("\n%s", markdown(report))


if __name__ == "__main__":
    main()

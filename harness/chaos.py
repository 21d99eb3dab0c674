"""The chaos harness: N jobs on W workers in Redis mode while things break, and what the jobs'
records and event logs say afterwards. ``python -m bench.chaos`` runs it at full size and writes
``bench/results/chaos.*``; ``tests/e2e/test_chaos.py`` runs a short version and asserts on its report.

What breaks: every ``kill_every`` seconds a worker that is running a job is SIGKILLed and a new
worker process is started under the same name; once, Redis is killed and restarted empty (no
persistence) while workers are busy; once, a busy worker's writes start failing with EFBIG (its
file-size limit is lowered with ``prlimit``: the folder store raises ``StoreFull``, as on ENOSPC),
until its job failed; then the limit is lifted and the same worker must go on.

What it reports (events name the attempt that wrote them): finished, failed (and why), lost (not
finished when the run ends), *overlapping writers* (an attempt that wrote after its successor had
started: must be 0), per kill the takeover time (kill to the next attempt's ``running``) and the
work redone (iterations the dead attempt had recorded that the next one computed again, and
seconds since its last checkpoint).
"""

from __future__ import annotations

import json
import logging
import random
import resource
import tempfile
import time
from dataclasses import asdict, dataclass, field
from datetime import UTC, datetime
from pathlib import Path

from harness.cluster import Api, Redis, small_job, start_api, start_worker, wait_until

log = logging.getLogger(__name__)
FINISHED = {"succeeded", "failed", "canceled"}
DISK_FULL_BYTES = 16 << 10


@dataclass
class ChaosConfig:
    jobs: int = 10
    workers: int = 3
    iterations: int = 60
    kill_every: float = 60.0
    max_kills: int | None = None          # None: keep killing until the jobs are done
    redis_restart_after: float | None = 90.0    # seconds after the start (then: when >= 2 workers are busy)
    kills_before_redis: int = 0           # and not before this many kills
    disk_full_after: float | None = 150.0
    lease_seconds: float = 10.0
    max_attempts: int = 20                # the kills are ours, not the jobs': do not fail a job for them
    timeout: float = 3600.0
    seed: int = 0
    folder: str | None = None
    keys: int = 2                         # tenant keys; job i is submitted by key i mod keys
    running_per_key: int = 2              # quotas on: NDRF_MAX_RUNNING_JOBS_PER_KEY
    key_bytes: int = 256 << 20            # and NDRF_MAX_KEY_BYTES


@dataclass
class Incident:
    kind: str                             # kill | redis-restart | disk-full
    at: str                               # ISO time
    worker: str | None = None
    job: str | None = None
    attempt: str | None = None
    detail: dict = field(default_factory=dict)


def now_iso() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _seconds(a: str, b: str) -> float:
    return (datetime.fromisoformat(b) - datetime.fromisoformat(a)).total_seconds()


class Chaos:
    def __init__(self, config: ChaosConfig):
        self.config = config
        self.random = random.Random(config.seed)
        self.folder = Path(config.folder or tempfile.mkdtemp(prefix="ndrf-chaos-"))
        self.folder.mkdir(parents=True, exist_ok=True)
        self.store = self.folder / "store"
        self.incidents: list[Incident] = []
        self.dead: set[tuple[str, str]] = set()   # (job, attempt) we killed: a restarted worker reuses the name
        self.redis = Redis().start()
        self.env = {"REDIS_URL": self.redis.url, "NDRF_STORE": str(self.store),
                    "NDRF_LEASE_SECONDS": str(config.lease_seconds), "NDRF_MAX_ATTEMPTS": str(config.max_attempts),
                    "NDRF_SCRATCH": str(self.folder / "scratch"),
                    "NDRF_API_KEYS": ",".join(f"chaos-{k}" for k in range(config.keys)),
                    "NDRF_MAX_RUNNING_JOBS_PER_KEY": str(config.running_per_key),
                    "NDRF_MAX_KEY_BYTES": str(config.key_bytes)}
        self.api_proc, self.api = start_api(self.folder, self.env)
        self.tenants = [Api(self.api.base, f"chaos-{k}") for k in range(config.keys)]
        self.workers = {f"w{i}": start_worker(self.folder, self.env, f"w{i}") for i in range(config.workers)}

    # ------------------------------------------------------------------ reads

    def record(self, job_id: str) -> dict:
        try:
            return json.loads((self.store / job_id / "record.json").read_text())
        except (OSError, ValueError):
            return {}

    def events(self, job_id: str) -> list[dict]:
        path = self.store / job_id / "events.jsonl"
        out = []
        for line in path.read_text().splitlines():
            try:
                out.append(json.loads(line))
            except ValueError:
                continue
        return out

    def running(self, ids: list[str], iterating: bool = True) -> list[dict]:
        """Records of running jobs whose worker is one of ours and alive (``iterating``: with an
        iteration done, so a kill has a checkpoint to lose work from)."""
        out = []
        for job_id in ids:
            rec = self.record(job_id)
            worker = self.workers.get(rec.get("worker") or "")
            if rec.get("status") == "running" and worker is not None and worker.alive() \
                    and (job_id, rec.get("attempt")) not in self.dead \
                    and (not iterating or (rec.get("iteration") if rec.get("iteration") is not None else -1) >= 0):
                out.append(rec)
        return out

    # ---------------------------------------------------------------- faults

    def kill(self, rec: dict) -> None:
        name = rec["worker"]
        self.workers[name].kill()
        self.dead.add((rec["id"], rec["attempt"]))
        self.incidents.append(Incident("kill", now_iso(), name, rec["id"], rec["attempt"],
                                       {"iteration": rec.get("iteration")}))
        log.info("killed %s running %s (%s, iteration %s)", name, rec["id"], rec["attempt"], rec.get("iteration"))
        self.workers[name] = start_worker(self.folder, self.env, name)

    def restart_redis(self, busy: list[dict]) -> None:
        self.redis.kill()
        at = now_iso()
        time.sleep(1.0)
        self.redis.start()
        self.incidents.append(Incident("redis-restart", at, detail={"running": [(r["id"], r["attempt"]) for r in busy]}))
        log.info("restarted Redis empty while %d job(s) ran", len(busy))

    def disk_full(self, rec: dict, ids: list[str]) -> None:
        name = rec["worker"]
        pid = self.workers[name].pid
        hard = resource.prlimit(pid, resource.RLIMIT_FSIZE)[1]      # lower the soft limit only: it can be raised back
        resource.prlimit(pid, resource.RLIMIT_FSIZE, (DISK_FULL_BYTES, hard))
        incident = Incident("disk-full", now_iso(), name, rec["id"], rec["attempt"])
        log.info("disk full for %s (pid %d) running %s", name, pid, rec["id"])
        try:
            wait_until(lambda: self.record(rec["id"]).get("status") != "running"
                       or self.record(rec["id"]).get("attempt") != rec["attempt"], 120, 0.5, what="the write failure")
        except TimeoutError:
            incident.detail["timeout"] = True
        finally:
            resource.prlimit(pid, resource.RLIMIT_FSIZE, (hard, hard))
        incident.detail.update(ended=now_iso(), status=self.record(rec["id"]).get("status"),
                               error=self.record(rec["id"]).get("error"), pid=pid)
        self.incidents.append(incident)

    # ------------------------------------------------------------------- run

    def run(self) -> dict:
        config = self.config
        started = time.monotonic()
        ids = []
        for i in range(config.jobs):
            tenant = self.tenants[i % len(self.tenants)]
            status, _, body = tenant.json("POST", "/v1/jobs", small_job(iterations=config.iterations, seed=i + 1))
            assert status == 202, body
            ids.append(body["id"])
        next_kill = started + config.kill_every
        kills = 0
        redis_done = config.redis_restart_after is None
        disk_done = config.disk_full_after is None
        while time.monotonic() - started < config.timeout:
            if all(self.record(j).get("status") in FINISHED for j in ids):
                break
            now = time.monotonic()
            busy = self.running(ids)
            if not disk_done and now - started >= config.disk_full_after and busy:  # type: ignore[operator]
                self.disk_full(self.random.choice(busy), ids)
                disk_done = True
                continue
            started_jobs = self.running(ids, iterating=False)
            if not redis_done and now - started >= config.redis_restart_after and kills >= config.kills_before_redis \
                    and len(started_jobs) >= min(2, config.workers):  # type: ignore[operator]
                self.restart_redis(started_jobs)
                redis_done = True
                continue
            if now >= next_kill and busy and (config.max_kills is None or kills < config.max_kills):
                self.kill(self.random.choice(busy))
                kills += 1
                next_kill = now + config.kill_every
                continue
            time.sleep(0.3)
        elapsed = time.monotonic() - started
        return self.report(ids, elapsed)

    def close(self) -> None:
        for worker in self.workers.values():
            worker.kill()
        self.api_proc.kill()
        self.redis.kill()

    # ---------------------------------------------------------------- report

    def report(self, ids: list[str], elapsed: float) -> dict:
        disk_victims = {i.job for i in self.incidents if i.kind == "disk-full"}
        jobs, overlaps = [], 0
        for job_id in ids:
            rec, events = self.record(job_id), self.events(job_id)
            order: list[str] = []
            for event in events:
                attempt = event.get("attempt")
                if not attempt:
                    continue
                if order and attempt != order[-1] and attempt in order:
                    overlaps += 1          # an earlier attempt wrote again after its successor started
                if not order or order[-1] != attempt:
                    order.append(attempt)
            jobs.append({"id": job_id, "status": rec.get("status"), "error": rec.get("error"),
                         "attempts": rec.get("attempts"), "crashes": rec.get("crashes"), "writers": order,
                         "disk_full_victim": job_id in disk_victims})
        kills = [self._kill_cost(i) for i in self.incidents if i.kind == "kill"]
        failed = [j for j in jobs if j["status"] == "failed"]
        worker_logs = "".join(p.read_text(errors="replace") for p in self.folder.glob("w*.log"))
        return {
            "config": asdict(self.config), "seconds": round(elapsed, 1), "folder": str(self.folder),
            "jobs": len(ids),
            "succeeded": sum(j["status"] == "succeeded" for j in jobs),
            "failed": len(failed),
            "failed_healthy": [j for j in failed if not j["disk_full_victim"]],
            "failed_why": [{"job": j["id"], "error": j["error"], "injected": j["disk_full_victim"]} for j in failed],
            "lost": [j["id"] for j in jobs if j["status"] not in FINISHED],
            "overlapping_writers": overlaps,
            "kills": kills,
            "incidents": [asdict(i) for i in self.incidents],
            "adopted_after_redis_restart": worker_logs.count("Redis restarted empty"),
            "handed_back_lease_lost": sum(e.get("note", "").startswith("lease lost") for j in ids
                                          for e in self.events(j)),
            "disk_full_worker_went_on": self._went_on(),
            "per_job": jobs,
        }

    def _kill_cost(self, kill: Incident) -> dict:
        events = self.events(kill.job or "")
        mine = [e for e in events if e.get("attempt") == kill.attempt]
        later = [e for e in events if e.get("attempt") not in (None, kill.attempt) and e["time"] > kill.at]
        nxt = next((e for e in later if e.get("type") == "status" and e.get("status") == "running"), None)
        resumed = next((e for e in later if e.get("type") == "resumed"), None)
        done = [e["iteration"] for e in mine if e.get("type") == "iteration"]
        checkpoints = [e for e in mine if e.get("type") == "checkpoint"]
        start = next((e["iteration"] for e in [resumed] if e), 0)
        return {"job": kill.job, "attempt": kill.attempt, "successor": nxt.get("attempt") if nxt else None,
                "takeover_seconds": round(_seconds(kill.at, nxt["time"]), 1) if nxt else None,
                "iterations_redone": sum(1 for k in done if k >= start),
                "seconds_since_checkpoint": round(_seconds(checkpoints[-1]["time"], kill.at), 1) if checkpoints else None}

    def _went_on(self) -> bool | None:
        """After the disk-full episode, the same worker process started another attempt (or none was left)."""
        for incident in self.incidents:
            if incident.kind != "disk-full":
                continue
            log_text = (self.folder / f"{incident.worker}.log").read_text(errors="replace")
            after = log_text.split(f"runs job {incident.job}", 1)[-1]
            return " runs job " in after or "queue empty" in after or incident.detail.get("pid") is None
        return None


def run(config: ChaosConfig) -> dict:
    chaos = Chaos(config)
    try:
        return chaos.run()
    finally:
        chaos.close()


def markdown(report: dict) -> str:
    c = report["config"]
    lines = [f"### Chaos: {report['jobs']} jobs x {c['iterations']} iterations, {c['workers']} workers, "
             f"a SIGKILL every {c['kill_every']:g} s, lease {c['lease_seconds']:g} s, {c.get('keys', 1)} keys at "
             f"{c.get('running_per_key', 0)} running jobs and {c.get('key_bytes', 0) >> 20} MiB each "
             f"({report['seconds']:.0f} s)", "",
             "| jobs | succeeded | failed (injected disk full) | failed healthy | lost | overlapping writers | "
             "kills | adopted after Redis restart |",
             "|---|---|---|---|---|---|---|---|",
             f"| {report['jobs']} | {report['succeeded']} | {report['failed']} "
             f"({sum(f['injected'] for f in report['failed_why'])}) | {len(report['failed_healthy'])} | "
             f"{len(report['lost'])} | {report['overlapping_writers']} | {len(report['kills'])} | "
             f"{report['adopted_after_redis_restart']} |", ""]
    kills = report["kills"]
    if kills:
        lines += ["| kill | job | takeover (s) | iterations redone | seconds since last checkpoint |",
                  "|---|---|---|---|---|"]
        for i, k in enumerate(kills, 1):
            lines.append(f"| {i} | {k['job']} | {k['takeover_seconds']} | {k['iterations_redone']} | "
                         f"{k['seconds_since_checkpoint']} |")
        takeovers = sorted(k["takeover_seconds"] for k in kills if k["takeover_seconds"] is not None)
        if takeovers:
            lines.append(f"\ntakeover median {takeovers[len(takeovers) // 2]:.1f} s, max {takeovers[-1]:.1f} s; "
                         f"iterations redone per kill: mean {sum(k['iterations_redone'] for k in kills) / len(kills):.2f}")
    for f in report["failed_why"]:
        lines.append(f"\nfailed {f['job']}{' (injected disk full)' if f['injected'] else ''}: {f['error']}")
    if report["disk_full_worker_went_on"] is not None:
        lines.append(f"\nthe disk-full worker went on afterwards: {report['disk_full_worker_went_on']}")
    return "\n".join(lines) + "\n"

"""``/healthz`` and ``/metrics`` (Prometheus text format).

Both name the device this process's children run on (:mod:`services.jobs.device`, probed once).
``/metrics`` is cheap: job counts, phase timings and the store's size come from a snapshot that a
background thread refreshes every ``SNAPSHOT_SECONDS`` (one scan of the store per period, whatever
the scrape rate). With ``NDRF_METRICS_PUBLIC=false`` it needs an admin key.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import Counter

from fastapi import APIRouter, Request
from fastapi.responses import JSONResponse, PlainTextResponse
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import GaugeMetricFamily, SummaryMetricFamily
from pydantic import BaseModel, Field

from api.deps import RuntimeDep, SettingsDep, require_admin
from schemas.records import JobStatus

log = logging.getLogger(__name__)
router = APIRouter(tags=["health"])

SNAPSHOT_SECONDS = 30.0


class Health(BaseModel):
    status: str = Field(description="'ok' when the store is writable, the queue reachable and (embedded) the "
                                    "job runners alive.")
    mode: str = Field(description="'redis' or 'embedded'.")
    queue: dict[str, int] | None = Field(None, description="Jobs waiting and leased.")
    detail: str | None = Field(None, description="Which part is unavailable, when not ok (no internals).")
    runner_restarts: int | None = Field(None, description="Embedded mode: job runner threads that died and were "
                                                          "restarted since the API started.")
    device: dict | None = Field(None, description="The device this process's children run on (jobs in embedded "
                                                  "mode, views, scene checks): {device: cpu or cuda, name, variant, "
                                                  "requested: NDRF_DEVICE, reason}, probed once in a child at the "
                                                  "first /healthz (null until known). Workers log theirs at "
                                                  "start-up; each job's plan.json names its own.")


@router.get("/healthz", response_model=Health, responses={503: {"model": Health}})
def healthz(request: Request, runtime: RuntimeDep):
    mode = "embedded" if runtime.embedded else "redis"
    device = request.app.state.device.get()
    part = "store"
    try:
        runtime.store.put(".healthz", b"ok")
        part = "queue"
        depth = runtime.queue.depth()
    except Exception:  # the reason goes to the log, not to anonymous clients
        log.exception("health check: %s unavailable", part)
        return JSONResponse(Health(status="unavailable", mode=mode, detail=f"{part} unavailable",
                                   device=device).model_dump(), status_code=503)
    restarts = runtime.runner_restarts if runtime.embedded else None
    dead = [t.name for t in runtime.threads if t is not None and not t.is_alive()]
    if dead:   # the supervisor restarts it within a second or so
        return JSONResponse(Health(status="unavailable", mode=mode, queue=depth, runner_restarts=restarts,
                                   detail=f"{len(dead)} job runner(s) stopped; restarting", device=device).model_dump(),
                            status_code=503)
    detail = f"{restarts} job runner restart(s) since start-up" if restarts else None
    return Health(status="ok", mode=mode, queue=depth, runner_restarts=restarts, detail=detail, device=device)


class Snapshot:
    """Job counts by status, recent phase seconds of running jobs, store bytes: refreshed in the
    background, read by every scrape."""

    def __init__(self, runtime):
        self.runtime = runtime
        self.counts: Counter = Counter()
        self.phases: dict[str, list[float]] = {}
        self.store_bytes = 0
        self.taken = 0.0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def ensure_running(self) -> None:
        with self._lock:
            if self._thread is None:
                self.refresh()
                self._thread = threading.Thread(target=self._loop, name="metrics-snapshot", daemon=True)
                self._thread.start()

    def _loop(self) -> None:
        while True:
            time.sleep(SNAPSHOT_SECONDS)
            try:
                self.refresh()
            except Exception as exc:
                log.warning("metrics snapshot failed: %s", exc)

    def refresh(self) -> None:
        service = self.runtime.service
        counts: Counter[str] = Counter()
        phases: dict[str, list[float]] = {}
        for record in service.records():
            counts[record.status.value] += 1
            if record.status is JobStatus.RUNNING and record.iteration is not None:
                latest = service.states.files(record.id).iteration_record(record.iteration) or {}
                for phase, value in latest.get("seconds", {}).items():
                    phases.setdefault(phase, []).append(value)
        self.counts, self.phases = counts, phases
        self.store_bytes = self.runtime.store.usage_bytes()
        self.taken = time.time()


class ServiceCollector:
    def __init__(self, runtime, snapshot: Snapshot, device: dict | None = None):
        self.runtime, self.snapshot, self.device = runtime, snapshot, device

    def collect(self):
        queue = GaugeMetricFamily("ndrf_queue_depth", "Jobs in the queue.", labels=["state"])
        for state, value in self.runtime.queue.depth().items():
            queue.add_metric([state], value)
        yield queue
        jobs = GaugeMetricFamily("ndrf_jobs", "Jobs in the store by status (snapshot).", labels=["status"])
        for status in JobStatus:
            jobs.add_metric([status.value], self.snapshot.counts.get(status.value, 0))
        yield jobs
        seconds = SummaryMetricFamily("ndrf_iteration_seconds", "Seconds per phase of the latest iteration of "
                                      "running jobs (snapshot).", labels=["phase"])
        for phase in ("training", "gradient", "images"):
            values = self.snapshot.phases.get(phase, [])
            seconds.add_metric([phase], count_value=len(values), sum_value=sum(values))
        yield seconds
        yield GaugeMetricFamily("ndrf_store_bytes", "Bytes in the artifact store (snapshot).",
                                value=self.snapshot.store_bytes)
        yield GaugeMetricFamily("ndrf_metrics_snapshot_age_seconds", "Age of the snapshot.",
                                value=time.time() - self.snapshot.taken)
        info = GaugeMetricFamily("ndrf_device_info", "The device this process's children run on (1; absent until "
                                 "probed, see /healthz).", labels=["device", "name", "requested"])
        if self.device is not None:
            info.add_metric([str(self.device.get("device", "")), str(self.device.get("name", "")),
                             str(self.device.get("requested", ""))], 1)
        yield info


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics")
def metrics(request: Request, runtime: RuntimeDep, settings: SettingsDep):
    if not settings.metrics_public:
        require_admin(request, settings)
    snapshot = request.app.state.snapshot
    snapshot.ensure_running()
    registry = CollectorRegistry()
    registry.register(ServiceCollector(runtime, snapshot, request.app.state.device.get()))
    return PlainTextResponse(generate_latest(registry).decode(), media_type="text/plain; version=0.0.4")

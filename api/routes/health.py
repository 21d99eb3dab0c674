"""``/healthz`` and ``/metrics`` (Prometheus text format)."""

from __future__ import annotations

from collections import Counter

from fastapi import APIRouter
from fastapi.responses import PlainTextResponse
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.core import GaugeMetricFamily, SummaryMetricFamily
from pydantic import BaseModel, Field

from api.deps import RuntimeDep
from schemas.records import JobStatus

router = APIRouter(tags=["health"])

STATUSES: tuple[str, ...] = JobStatus.__args__  # type: ignore[attr-defined]


class Health(BaseModel):
    status: str = Field(description="'ok' when the store is writable and the queue reachable.")
    mode: str = Field(description="'redis' or 'embedded'.")
    queue: dict[str, int] | None = Field(None, description="Jobs waiting and leased.")
    detail: str | None = Field(None, description="What is wrong, when not ok.")


@router.get("/healthz", response_model=Health, responses={503: {"model": Health}})
def healthz(runtime: RuntimeDep):
    mode = "embedded" if runtime.embedded else "redis"
    try:
        probe = runtime.settings.store / ".healthz"
        probe.write_text("ok")
        depth = runtime.queue.depth()
    except Exception as exc:  # any failure of the store or Redis is "not healthy", with the reason
        from fastapi.responses import JSONResponse

        return JSONResponse(Health(status="unavailable", mode=mode, detail=str(exc)).model_dump(), status_code=503)
    return Health(status="ok", mode=mode, queue=depth)


class ServiceCollector:
    """Computed at scrape time from the store (the source of truth) and the queue."""

    def __init__(self, runtime):
        self.runtime = runtime

    def collect(self):
        depth = self.runtime.queue.depth()
        queue = GaugeMetricFamily("ndrf_queue_depth", "Jobs in the queue.", labels=["state"])
        for state, value in depth.items():
            queue.add_metric([state], value)
        yield queue

        records = list(self.runtime.service.records())
        counts = Counter(r.get("status") for r in records)
        jobs = GaugeMetricFamily("ndrf_jobs", "Jobs in the store by status.", labels=["status"])
        for status in STATUSES:
            jobs.add_metric([status], counts.get(status, 0))
        yield jobs

        seconds = SummaryMetricFamily("ndrf_iteration_seconds", "Seconds per iteration phase of running jobs.",
                                      labels=["phase"])
        totals: dict[str, list[float]] = {}
        for record in records:
            if record.get("status") != "running":
                continue
            folder = self.runtime.service.folder(record["id"])
            for k in folder.iterations()[-100:]:
                for phase, value in (folder.iteration_record(k) or {}).get("seconds", {}).items():
                    totals.setdefault(phase, []).append(value)
        for phase in ("training", "rendering", "gradient"):
            values = totals.get(phase, [])
            seconds.add_metric([phase], count_value=len(values), sum_value=sum(values))
        yield seconds


@router.get("/metrics", response_class=PlainTextResponse, summary="Prometheus metrics")
def metrics(runtime: RuntimeDep):
    registry = CollectorRegistry()
    registry.register(ServiceCollector(runtime))
    return PlainTextResponse(generate_latest(registry).decode(), media_type="text/plain; version=0.0.4")

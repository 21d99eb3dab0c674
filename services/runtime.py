"""Wiring of one process: the store, the queue and the event bus chosen by the settings.

With ``REDIS_URL`` set, the queue and event streams live in Redis (several workers on several
machines); without it, the embedded default keeps both in-process and ``ndrf serve`` runs jobs on
worker threads of its own.
"""

from __future__ import annotations

import logging
import threading
import time
from dataclasses import dataclass, field

from services.jobs import JobService
from services.queue.base import EventBus, JobQueue
from services.settings import Settings

log = logging.getLogger(__name__)


@dataclass
class Runtime:
    settings: Settings
    service: JobService
    queue: JobQueue
    events: EventBus
    redis: object | None = None
    workers: list = field(default_factory=list)
    threads: list = field(default_factory=list)
    _last_reconcile: float = field(default=float("-inf"), repr=False)

    @property
    def embedded(self) -> bool:
        return self.redis is None

    def start_embedded_workers(self) -> None:
        """Worker threads inside this process (embedded mode only)."""
        from worker.main import Worker

        for i in range(self.settings.embedded_workers):
            worker = Worker(self.service, self.queue, self.events, lease_seconds=self.settings.lease_seconds,
                            max_attempts=self.settings.max_attempts, name=f"embedded-{i}")
            thread = threading.Thread(target=worker.work, name=f"ndrf-worker-{i}", daemon=True)
            thread.start()
            self.workers.append(worker)
            self.threads.append(thread)

    def reconcile_periodically(self, every: float = 30.0) -> None:
        """Re-enqueue lost jobs (Redis restarted without persistence), at most every ``every``
        seconds across all workers: a Redis lock elects one reconciler per period."""
        if self.redis is None:
            return
        now = time.monotonic()
        if now - self._last_reconcile < every / 3:
            return
        self._last_reconcile = now
        try:
            if self.redis.set("ndrf:reconcile-lock", "1", nx=True, ex=max(1, int(every))):
                self.service.reconcile()
        except Exception as exc:  # Redis down: the next period tries again
            log.warning("reconciler skipped: %s", exc)

    def stop(self, timeout: float = 30.0) -> None:
        for worker in self.workers:
            worker.request_stop()
        for thread in self.threads:
            thread.join(timeout)
        if self.redis is not None:
            self.redis.close()


def build_runtime(settings: Settings) -> Runtime:
    settings.store.mkdir(parents=True, exist_ok=True)
    if settings.redis_url:
        from services.queue.redis_queue import RedisEventBus, RedisJobQueue, connect

        client = connect(settings.redis_url)
        queue, events = RedisJobQueue(client, settings.lease_seconds), RedisEventBus(client)
        runtime = Runtime(settings, JobService(settings.store, queue, events), queue, events, redis=client)
    else:
        from services.queue.local import LocalEventBus, LocalJobQueue

        queue, events = LocalJobQueue(), LocalEventBus()
        runtime = Runtime(settings, JobService(settings.store, queue, events), queue, events)
    log.info("runtime: store %s, %s", settings.store, "redis" if settings.redis_url else "embedded")
    return runtime

"""Wiring of one process: the store, the queue and the event bus chosen by the settings.

With ``REDIS_URL`` set, the queue and event streams live in Redis (several workers on several
machines); without it, the embedded default keeps both in-process and ``ndrf serve`` runs jobs on
worker threads of its own (each job still in its own sandboxed child process). The worker is
passed in as a factory: this module does not import the entry points.
"""

from __future__ import annotations

import logging
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

from services.jobs.service import JobService
from services.queue.base import EventBus, JobQueue, StreamSlots
from services.settings import Settings
from services.store.base import ArtifactStore

if TYPE_CHECKING:
    import redis

log = logging.getLogger(__name__)

#: ``factory(runtime, name) -> worker`` with ``work()`` and ``request_stop()`` (``worker.main.Worker``).
WorkerFactory = Callable[["Runtime", str], Any]


def open_store(settings: Settings) -> ArtifactStore:
    """The artifact store ``NDRF_STORE`` names: ``s3://bucket/prefix`` or a folder. The S3 client
    is imported only when an S3 store is configured."""
    if settings.store.startswith("s3://"):
        from services.store.s3 import S3Store

        return S3Store(settings.store, endpoint=settings.s3_endpoint or None, presign_bytes=settings.s3_presign_bytes,
                       presign_seconds=settings.s3_presign_seconds,
                       public_endpoint=settings.s3_public_endpoint or None, usage_ttl=settings.s3_usage_seconds)
    if "://" in settings.store:
        raise ValueError(f"NDRF_STORE={settings.store!r}: a folder path or s3://bucket/prefix")
    from services.store.local import FolderStore

    return FolderStore(settings.store)


def scratch_folder(settings: Settings) -> Path:
    """Where this machine stages scenes for its sandboxed processes (never the source of truth)."""
    path = Path(settings.scratch) if settings.scratch else Path(tempfile.gettempdir()) / "ndrf-scratch"
    path.mkdir(parents=True, exist_ok=True)
    return path


@dataclass
class Runtime:
    settings: Settings
    store: ArtifactStore
    service: JobService
    queue: JobQueue
    events: EventBus
    slots: StreamSlots | None = None
    redis: redis.Redis | None = None  # the client of REDIS_URL (None: the embedded default)
    blocking: Any = None  # the API's limiter of blocking work (an anyio CapacityLimiter)
    admission: Any = None  # the same work in a line per key first (api.admission.Admission)
    workers: list = field(default_factory=list)
    threads: list = field(default_factory=list)
    runner_restarts: int = 0
    runner_failure: str | None = None   # why the last embedded runner thread died
    _stopping: threading.Event = field(default_factory=threading.Event, repr=False)
    _last_reconcile: float = field(default=float("-inf"), repr=False)
    _last_sweep: float = field(default=float("-inf"), repr=False)
    _experiments: Any = field(default=None, repr=False)
    scheduler: Any = None  # services.experiments.scheduler.Scheduler, once started
    _view_sessions: Any = field(default=None, repr=False)
    scheduler_thread: threading.Thread | None = None

    @property
    def embedded(self) -> bool:
        return self.redis is None

    @property
    def reconcile_grace(self) -> float:
        """How long a job must stay missing from the queue before the reconciler re-enqueues it:
        two lease periods, in which a live attempt re-registers itself (renewals come every lease/3)."""
        return 2 * self.settings.lease_seconds

    @property
    def experiments(self):
        """The experiment service (:mod:`services.experiments`) over this runtime's jobs."""
        if self._experiments is None:
            from services.experiments.service import ExperimentService

            self._experiments = ExperimentService(self.service, self.settings.limits)
        return self._experiments

    @property
    def view_sessions(self):
        """This process's warm view children (:mod:`services.jobs.view_sessions`)."""
        if self._view_sessions is None:
            from services.jobs.view_sessions import ViewSessions

            self._view_sessions = ViewSessions(self.settings.view_keep_seconds, self.settings.view_children)
        return self._view_sessions

    def start_experiment_scheduler(self, interval: float = 0.5) -> None:
        """Admit experiment runs from this process (API processes and workers all run one; with
        Redis a lease elects the one that ticks)."""
        from services.experiments.scheduler import RedisLeader, Scheduler

        leader = RedisLeader(self.redis) if self.redis is not None else None
        self.scheduler = Scheduler(self.experiments, self.queue, interval=interval, leader=leader)
        self.scheduler_thread = self.scheduler.start()


    # ---------------------------------------------------------- embedded runners

    def start_embedded_workers(self, factory: WorkerFactory, check_every: float = 1.0) -> None:
        """Worker threads inside this process (embedded mode only), and a supervisor thread that
        restarts a runner thread that died (its job is taken over once its lease expires)."""
        for i in range(self.settings.embedded_workers):
            self.workers.append(None)
            self.threads.append(None)
            self._start_runner(factory, i)
        threading.Thread(target=self._supervise, args=(factory, check_every), name="ndrf-runner-supervisor",
                         daemon=True).start()

    def _start_runner(self, factory: WorkerFactory, i: int) -> None:
        worker = factory(self, f"embedded-{i}")

        def run() -> None:
            try:
                worker.work()
            except BaseException as exc:  # the thread ends here; the supervisor starts a new one
                self.runner_failure = f"{type(exc).__name__}: {exc}"
                log.exception("embedded runner %d died", i)

        thread = threading.Thread(target=run, name=f"ndrf-worker-{i}", daemon=True)
        self.workers[i], self.threads[i] = worker, thread
        thread.start()

    def _supervise(self, factory: WorkerFactory, every: float) -> None:
        while not self._stopping.wait(every):
            for i, thread in enumerate(self.threads):
                if thread is not None and not thread.is_alive() and not self._stopping.is_set():
                    self.runner_restarts += 1
                    log.error("embedded runner %s died (%s); restarting it (restart %d)", thread.name,
                              self.runner_failure, self.runner_restarts)
                    try:
                        self._start_runner(factory, i)
                    except Exception:
                        log.exception("could not restart embedded runner %d", i)

    # ----------------------------------------------------------------- reconciler

    def reconcile_periodically(self, every: float | None = None) -> None:
        """Re-enqueue lost jobs (Redis restarted without persistence), at most every ``every``
        seconds (default: the lease, at least 5 s) across all workers: a Redis lock elects one
        reconciler per period; a job is re-enqueued only after :attr:`reconcile_grace`. The
        retention sweep runs here too."""
        every = every if every is not None else max(5.0, self.settings.lease_seconds)
        now = time.monotonic()
        if self.settings.retention_days and now - self._last_sweep > 3600:
            self._last_sweep = now
            try:
                self.service.sweep(self.settings.retention_days)
            except Exception as exc:
                log.warning("retention sweep skipped: %s", exc)
        if self.redis is None or now - self._last_reconcile < every / 3:
            return
        self._last_reconcile = now
        try:
            if self.redis.set("ndrf:reconcile-lock", "1", nx=True, ex=max(1, int(every))):
                self.service.reconcile(self.reconcile_grace)
        except Exception as exc:  # Redis down: the next period tries again
            log.warning("reconciler skipped: %s", exc)

    def stop(self, timeout: float = 30.0) -> None:
        self._stopping.set()
        if self.scheduler is not None:
            self.scheduler.stop()
        if self._view_sessions is not None:
            self._view_sessions.close()
        for worker in self.workers:
            if worker is not None:
                worker.request_stop()
        for thread in self.threads:
            if thread is not None:
                thread.join(timeout)
        if self.redis is not None:
            self.redis.close()
        self.store.close()


def build_runtime(settings: Settings) -> Runtime:
    store = open_store(settings)
    if settings.redis_url:
        from services.queue.redis_queue import RedisEventBus, RedisJobQueue, RedisStreamSlots, connect

        client = connect(settings.redis_url)
        bus = RedisEventBus(client, settings.redis_url, connections=settings.redis_connections)
        queue: JobQueue = RedisJobQueue(client, settings.lease_seconds, settings.limits.running_jobs_per_key)
        runtime = Runtime(settings, store, JobService(store, queue, bus), queue, bus, slots=RedisStreamSlots(bus),
                          redis=client)
    else:
        from services.queue.local import LocalEventBus, LocalJobQueue, LocalStreamSlots

        queue, events = LocalJobQueue(settings.lease_seconds, settings.limits.running_jobs_per_key), LocalEventBus()
        runtime = Runtime(settings, store, JobService(store, queue, events), queue, events, slots=LocalStreamSlots())
    log.info("runtime: store %r, %s", store, "redis" if settings.redis_url else "embedded")
    return runtime

"""One worker: lease a job, run an attempt of it with a renewed lease, ack it; repeat.

A worker that dies (SIGKILL, OOM, power) stops renewing its lease and its attempt's heartbeat;
after ``lease_seconds`` another worker's ``lease`` takes the job over and resumes it from its last
checkpoint. A crash is counted only when the attempt the record names has no live heartbeat: a
delivery of a job whose attempt still beats is a duplicate and is dropped. Every
attempt claims the job in its record (``attempt``), and every write of an attempt is fenced on it
(:mod:`services.jobs.state`), so a stale attempt cannot overwrite its successor's files. A job
whose attempts keep dying is failed after ``max_attempts``. The job itself runs in a sandboxed
child process (:mod:`services.jobs.runner`): whatever the job does, the worker goes on.
SIGTERM/SIGINT stop the worker at the job's next training step: it is checkpointed and handed
back to the queue.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import uuid
from collections.abc import Callable
from pathlib import Path

from schemas.outcomes import Outcome
from schemas.records import ACTIVE, JobStatus
from services.jobs.device import DeviceReport
from services.jobs.isolation import sandbox_state
from services.jobs.runner import AttemptResult, AttemptRunner
from services.jobs.service import JobService
from services.jobs.state import Conflict, Fenced, UnknownJob
from services.queue.base import JobQueue, Lease, Renewal
from services.settings import Limits

log = logging.getLogger(__name__)


class Worker:
    def __init__(self, service: JobService, queue: JobQueue, *, limits: Limits, scratch: Path, lease_seconds: float,
                 max_attempts: int, name: str | None = None, reconcile: Callable[[], None] | None = None):
        self.service, self.queue = service, queue
        self.lease_seconds, self.max_attempts = lease_seconds, max_attempts
        self.name = name or f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        self.runner = AttemptRunner(service.states, limits, scratch)
        self.stopping = threading.Event()
        self.reconcile = reconcile or (lambda: None)
        self.consumer = f"{self.name}/{uuid.uuid4().hex[:8]}"   # unique even if a restarted worker reuses its name
        self.current: str | None = None
        self.attempt: str | None = None
        self.device = DeviceReport(on_known=lambda d: log.info(
            "worker %s: jobs run on %s (%s; NDRF_DEVICE=%s: %s)", self.name, d.get("device"), d.get("name", ""),
            d.get("requested", ""), d.get("reason", "")))

    # ---------------------------------------------------------------- the loop

    def work(self, burst: bool = False, install_signals: bool = False) -> str:
        """Process jobs until stopped (or, with ``burst``, until the queue is empty). Returns why it
        stopped."""
        if install_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: self.request_stop())
        log.info("worker %s started; child sandbox: %s", self.name, sandbox_state())
        if not burst:   # probed in the background (a child): the jobs' device, logged when known
            self.device.get()
        reason = "stopped"
        try:
            while not self.stopping.is_set():
                try:
                    self.reconcile()
                    lease = self.queue.lease(self.consumer, block_seconds=1.0 if burst else 5.0)
                except Exception as exc:  # the queue is unreachable (Redis restarting): wait and retry
                    log.warning("worker %s: queue unavailable (%s); retrying", self.name, exc)
                    self.stopping.wait(1.0)
                    continue
                if lease is None:
                    if burst:
                        reason = "queue empty (burst)"
                        break
                    continue
                self.perform(lease)
            else:
                reason = "stop requested"
        except BaseException as exc:
            reason = f"crashed: {type(exc).__name__}: {exc}"
            log.exception("worker %s crashed", self.name)
            raise
        finally:
            log.info("worker %s exits: %s", self.name, reason)
        return reason

    def request_stop(self) -> None:
        log.info("worker %s: stop requested, stopping the current job at its next training step", self.name)
        self.stopping.set()

    # ------------------------------------------------------------ one job

    def perform(self, lease: Lease) -> None:
        """Run one leased job; never raises for anything the job does (the job fails with it)."""
        self.current, self.attempt = lease.job_id, None
        try:
            self._perform(lease)
        except Exception as exc:  # a bug or an outage around the job: the job fails, the worker goes on
            log.exception("worker %s: job %s", self.name, lease.job_id)
            try:
                fence: dict[str, str] = {"fence": self.attempt} if self.attempt else {}
                self.service.states.transition(lease.job_id, JobStatus.FAILED, expect=ACTIVE, **fence,
                                               error=f"the worker failed running the job: {type(exc).__name__}: {exc}")
                self._ack(lease, self.attempt)
            except Exception as inner:  # the store is away too: the lease expires, another worker retries
                log.error("worker %s: could not record the failure of job %s: %s", self.name, lease.job_id, inner)
        finally:
            self.current = self.attempt = None

    def _perform(self, lease: Lease) -> None:
        states = self.service.states
        try:
            record = states.get(lease.job_id)
        except UnknownJob:
            log.warning("job %s is not in the store: dropping it from the queue", lease.job_id)
            return self._ack(lease)
        if record.status.finished:
            log.info("job %s is already %s: acking", lease.job_id, record.status.value)
            return self._ack(lease)
        running = record.status is JobStatus.RUNNING and record.attempt is not None
        if running and self.queue.alive(lease.job_id, str(record.attempt)):
            # Its attempt still beats: a duplicate delivery, not a crash. The live attempt holds
            # the job's marker; if it dies later, its own delivery (or the reconciler) brings it back.
            log.warning("job %s: attempt %s is alive; dropping delivery %s", lease.job_id, record.attempt,
                        lease.entry_id)
            return self._ack(lease)
        if record.cancel_requested:
            states.transition(lease.job_id, JobStatus.CANCELED, expect=ACTIVE)
            return self._ack(lease)
        crashes = record.crashes + running       # running, and its heartbeat expired: that attempt died
        if crashes >= self.max_attempts:
            states.transition(lease.job_id, JobStatus.FAILED, expect=ACTIVE, crashes=crashes,
                              error=f"the job crashed its worker {crashes} times (max_attempts={self.max_attempts}); "
                                    f"last attempt {record.attempt}")
            return self._ack(lease)
        attempt = f"{self.name}#{record.attempts + 1}"
        try:
            states.transition(lease.job_id, JobStatus.RUNNING, expect=ACTIVE, expect_attempt=record.attempt,
                              attempt=attempt, attempts=record.attempts + 1, crashes=crashes, worker=self.name,
                              note=f"took over from {record.attempt} (its heartbeat expired)" if running else None)
        except Conflict as exc:
            log.info("job %s: not claimed (%s)", lease.job_id, exc)
            return self._ack(lease)
        self.attempt = attempt
        log.info("worker %s runs job %s (attempt %s, delivery %d, took over from %s)", self.name, lease.job_id,
                 attempt, lease.delivery, record.attempt if running else None)
        result = self._run_with_lease(lease, attempt)
        if result.outcome is Outcome.FENCED:
            return self._fenced(lease, attempt)
        if result.outcome is Outcome.INTERRUPTED:
            return self._ack(lease, attempt, requeue=True)   # hand it back at once
        self._ack(lease, attempt)

    def _fenced(self, lease: Lease, attempt: str) -> None:
        """The attempt stopped without finishing: the lease was lost, or another attempt owns the
        record. If the record still names it, nobody took the job over yet: hand it back (not a
        crash). Ack only what is still ours (the new owner's delivery is left alone)."""
        states = self.service.states
        try:
            record = states.get(lease.job_id)
            if record.attempt == attempt and record.status is JobStatus.RUNNING:
                states.transition(lease.job_id, JobStatus.QUEUED, fence=attempt,
                                  note="lease lost; handed back, resumes from its checkpoint")
                self.queue.enqueue(lease.job_id, owner=record.owner)   # a no-op if the job is queued or leased
        except (Fenced, Conflict, UnknownJob) as exc:
            log.info("job %s: %s", lease.job_id, exc)
        self._ack(lease, attempt)

    def _run_with_lease(self, lease: Lease, attempt: str) -> AttemptResult:
        lost, done = threading.Event(), threading.Event()
        try:
            first = self.queue.renew(lease, attempt)   # the first heartbeat, before any work
        except Exception as exc:  # the queue is away: the heartbeat thread keeps trying
            log.warning("first lease renewal of job %s failed: %s", lease.job_id, exc)
            first = Renewal.KEPT
        if not first:
            return AttemptResult(Outcome.FENCED, "the lease was lost before the attempt started")
        heartbeat = threading.Thread(target=self._heartbeat, args=(lease, attempt, lost, done), daemon=True,
                                     name=f"lease-{lease.job_id}")
        heartbeat.start()

        def stop() -> Outcome | None:
            if self.service.cancel_requested(lease.job_id):
                return Outcome.CANCELED
            return Outcome.INTERRUPTED if self.stopping.is_set() else None

        try:
            return self.runner.run(lease.job_id, attempt, lost=lost, stop=stop)
        finally:
            done.set()
            heartbeat.join()

    def _ack(self, lease: Lease, attempt: str | None = None, requeue: bool = False) -> None:
        """Ack (or hand back) what is still ours, retrying briefly; if the queue stays away the
        entry is delivered again later and acked then (the record says the job is finished)."""
        for wait in (0.0, 0.5, 2.0):
            self.stopping.wait(wait)
            try:
                done = self.queue.requeue(lease, attempt) if requeue else self.queue.ack(lease, attempt)
                if not done:
                    log.info("job %s: delivery %s now belongs to another worker; left alone", lease.job_id,
                             lease.entry_id)
                return
            except Exception as exc:
                log.warning("ack of job %s failed: %s", lease.job_id, exc)

    def _heartbeat(self, lease: Lease, attempt: str, lost: threading.Event, done: threading.Event) -> None:
        while not done.wait(self.lease_seconds / 3):
            try:
                renewal = self.queue.renew(lease, attempt)
            except Exception as exc:  # Redis briefly unreachable: keep trying (ownership decides later)
                log.warning("lease renewal of job %s failed: %s", lease.job_id, exc)
                continue
            if renewal is Renewal.ADOPTED:
                log.warning("worker %s: the queue had lost job %s (Redis restarted empty); attempt %s goes on",
                            self.name, lease.job_id, attempt)
            elif not renewal:
                log.error("worker %s lost the lease of job %s", self.name, lease.job_id)
                lost.set()
                return


def make_worker(runtime, name: str | None = None) -> Worker:
    """A worker of a :class:`services.runtime.Runtime` (the factory the runtime's embedded mode and
    ``ndrf worker`` use)."""
    from services.runtime import scratch_folder

    settings = runtime.settings
    return Worker(runtime.service, runtime.queue, limits=settings.limits, scratch=scratch_folder(settings),
                  lease_seconds=settings.lease_seconds, max_attempts=settings.max_attempts, name=name,
                  reconcile=runtime.reconcile_periodically)

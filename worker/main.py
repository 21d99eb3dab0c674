"""One worker: lease a job, run it with a renewed lease, ack it; repeat.

A worker that dies (SIGKILL, OOM, power) stops renewing its lease; after ``lease_seconds``
another worker's ``lease`` takes the job over (XAUTOCLAIM) and resumes it from its last
checkpoint. Every attempt gets an id written into the job record; before every write, a run
checks that the record still names its attempt and that its lease is alive, so a stale attempt
cannot overwrite its successor's files. A job whose attempts keep dying is failed after
``max_attempts`` with a clear error. SIGTERM/SIGINT stop the worker at the next iteration
boundary: the job is checkpointed and handed back to the queue.
"""

from __future__ import annotations

import logging
import os
import signal
import socket
import threading
import uuid
from typing import Callable

from pydantic import ValidationError

from schemas.job import JobSpec
from schemas.records import FINISHED
from services.jobs import JobService, UnknownJob
from services.queue.base import EventBus, JobQueue, Lease
from services.store.layout import JobFolder, now_iso

log = logging.getLogger(__name__)


class Worker:
    def __init__(self, service: JobService, queue: JobQueue, events: EventBus, *, lease_seconds: float,
                 max_attempts: int, name: str | None = None, reconcile: Callable[[], None] | None = None):
        self.service, self.queue, self.events = service, queue, events
        self.lease_seconds, self.max_attempts = lease_seconds, max_attempts
        self.name = name or f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:6]}"
        self.stopping = threading.Event()
        self.reconcile = reconcile or (lambda: None)

    # ---------------------------------------------------------------- the loop

    def work(self, burst: bool = False, install_signals: bool = False) -> str:
        """Process jobs until stopped (or, with ``burst``, until the queue is empty). Returns why it
        stopped."""
        if install_signals:
            for sig in (signal.SIGTERM, signal.SIGINT):
                signal.signal(sig, lambda *_: self.request_stop())
        log.info("worker %s started", self.name)
        reason = "stopped"
        try:
            while not self.stopping.is_set():
                try:
                    self.reconcile()
                    lease = self.queue.lease(self.name, block_seconds=1.0 if burst else 5.0)
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
        except Exception:
            reason = "crashed"
            log.exception("worker %s crashed", self.name)
            raise
        finally:
            log.info("worker %s exits: %s", self.name, reason)
        return reason

    def request_stop(self) -> None:
        log.info("worker %s: stop requested, finishing the current iteration", self.name)
        self.stopping.set()

    # ------------------------------------------------------------ one job

    def perform(self, lease: Lease) -> None:
        try:
            folder = self.service.folder(lease.job_id)
        except UnknownJob:
            log.warning("job %s is not in the store: dropping it from the queue", lease.job_id)
            self.queue.ack(lease)
            return
        record = folder.read("record.json")
        if record["status"] in FINISHED:
            log.info("job %s is already %s: acking", lease.job_id, record["status"])
            self.queue.ack(lease)
            return
        if self.service.cancel_requested(folder):
            self._close(folder, record, "canceled", None)
            self.queue.ack(lease)
            return
        crashes = int(record.get("crashes", 0)) + (record["status"] == "running")
        if crashes >= self.max_attempts:
            self._close(folder, record, "failed",
                        f"the job crashed its worker {crashes} times (max_attempts={self.max_attempts}); "
                        f"last attempt {record.get('attempt')}")
            self.queue.ack(lease)
            return
        attempt = f"{self.name}#{int(record.get('attempts', 0)) + 1}"
        record.update(attempts=int(record.get("attempts", 0)) + 1, attempt=attempt, crashes=crashes,
                      worker=self.name, updated=now_iso())
        folder.write("record.json", record)
        log.info("worker %s runs job %s (attempt %s, delivery %d)", self.name, lease.job_id, attempt, lease.delivery)

        lost = threading.Event()
        done = threading.Event()
        heartbeat = threading.Thread(target=self._heartbeat, args=(lease, lost, done), daemon=True,
                                     name=f"lease-{lease.job_id}")
        heartbeat.start()
        try:
            outcome = self._run(folder, attempt, lost)
        finally:
            done.set()
            heartbeat.join()
        if outcome == "fenced":
            if folder.read("record.json", {}).get("attempt") == attempt:
                # Nobody took over: the lease vanished with Redis' data (a restart without
                # persistence). Not a crash: hand the job back, it resumes from its checkpoint.
                self._requeue(folder, lease.job_id, "lease lost (queue data lost); re-enqueued")
            return                                      # otherwise the new owner acks
        if outcome == "interrupted":
            self.queue.enqueue(lease.job_id)            # hand it back at once
        self._ack(lease)

    def _ack(self, lease: Lease) -> None:
        """Ack, retrying briefly; if the queue stays away the entry is delivered again later and
        acked then (the record says the job is finished)."""
        for wait in (0.0, 0.5, 2.0):
            self.stopping.wait(wait)
            try:
                self.queue.ack(lease)
                return
            except Exception as exc:
                log.warning("ack of job %s failed: %s", lease.job_id, exc)

    def _run(self, folder: JobFolder, attempt: str, lost: threading.Event) -> str:
        from services.optimize.loop import Fenced, InverseRenderingRun, RunHooks

        def guard() -> None:
            if lost.is_set() or folder.read("record.json", {}).get("attempt") != attempt:
                raise Fenced(attempt)

        def should_stop() -> str | None:
            if self.service.cancel_requested(folder):
                return "canceled"
            return "interrupted" if self.stopping.is_set() else None

        try:
            spec = JobSpec.model_validate(folder.read("spec.json"))
        except ValidationError as exc:
            self._close(folder, folder.read("record.json"), "failed", f"stored spec is invalid: {exc}")
            return "failed"
        hooks = RunHooks(on_event=lambda event: self.events.publish(folder.root.name, event),
                         should_stop=should_stop, guard=guard, attempt=attempt)
        try:
            summary = InverseRenderingRun(spec, folder, hooks).execute(resume=True)
        except Fenced:
            return "fenced"
        return summary["status"]

    def _requeue(self, folder: JobFolder, job_id: str, note: str) -> None:
        record = folder.read("record.json")
        record.update(status="queued", updated=now_iso())
        folder.write("record.json", record)
        self.events.publish(job_id, folder.append_event({"type": "status", "status": "queued", "note": note}))
        self.queue.enqueue(job_id)
        log.warning("job %s: %s", job_id, note)

    def _heartbeat(self, lease: Lease, lost: threading.Event, done: threading.Event) -> None:
        while not done.wait(self.lease_seconds / 3):
            try:
                if not self.queue.renew(lease, self.name):
                    log.error("worker %s lost the lease of job %s", self.name, lease.job_id)
                    lost.set()
                    return
            except Exception as exc:  # Redis briefly unreachable: keep trying until the lease would expire
                log.warning("lease renewal of job %s failed: %s", lease.job_id, exc)

    def _close(self, folder: JobFolder, record: dict, status: str, error: str | None) -> None:
        record.update(status=status, error=error, updated=now_iso())
        folder.write("record.json", record)
        event = folder.append_event({"type": "status", "status": status, "error": error})
        self.events.publish(folder.root.name, event)
        log.warning("job %s %s: %s", folder.root.name, status, error) if error else log.info(
            "job %s %s", folder.root.name, status)

"""A stand-in worker for the experiment scheduler's tests: it moves job records as the real
workers do (lease, running, a final status, ack), with no scene and no child process."""

from __future__ import annotations

import threading
import time

from schemas.job import JobSpec
from schemas.records import FINISHED, JobStatus
from services.jobs.service import JobService
from services.store.job import JobFiles


class FakeWorker:
    """Leases a job, runs it for ``hold`` seconds (checking cancel), fails it when ``fails(spec)``."""

    def __init__(self, service: JobService, hold: float, fails=lambda spec: False):
        self.service, self.hold, self.fails = service, hold, fails
        self.stop = threading.Event()
        self.thread = threading.Thread(target=self.work, daemon=True)
        self.thread.start()

    def work(self):
        states = self.service.states
        while not self.stop.is_set():
            lease = self.service.queue.lease("fake", 0.05)
            if lease is None:
                continue
            record = states.get(lease.job_id)
            if record.status in FINISHED:
                self.service.queue.ack(lease)
                continue
            if record.cancel_requested:
                states.transition(lease.job_id, JobStatus.CANCELED)
                self.service.queue.ack(lease)
                continue
            states.transition(lease.job_id, JobStatus.RUNNING, attempt="fake#1")
            end = time.monotonic() + self.hold
            while time.monotonic() < end and not states.get(lease.job_id).cancel_requested:
                time.sleep(0.01)
            spec = JobSpec.model_validate(JobFiles(self.service.store, lease.job_id).read(JobFiles.SPEC))
            if states.get(lease.job_id).cancel_requested:
                final = JobStatus.CANCELED
            else:
                final = JobStatus.FAILED if self.fails(spec) else JobStatus.SUCCEEDED
            states.transition(lease.job_id, final, error="boom" if final is JobStatus.FAILED else None)
            self.service.queue.ack(lease)

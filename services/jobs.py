"""The job service: submit, list, inspect and cancel jobs, over the store and the queue.

The store (one folder per job, :mod:`services.store.layout`) is the source of truth; the queue only
says which job a worker should pick up next. The API, the worker and the CLI all go through this
facade. No Mitsuba and no torch here: the API process starts without them.
"""

from __future__ import annotations

import hashlib
import logging
import os
import re
import secrets
import shutil
import time
from pathlib import Path
from typing import Iterator

from schemas.job import JobSpec
from schemas.records import FINISHED
from services.queue.base import EventBus, JobQueue
from services.store.files import atomic_write_bytes
from services.store.layout import JobFolder, now_iso

log = logging.getLogger(__name__)

JOB_ID = re.compile(r"^[0-9a-f]{20}$")


def new_job_id() -> str:
    """20 hex characters: milliseconds since the epoch (12) then randomness (8): sorts by time."""
    return f"{int(time.time() * 1000):012x}{secrets.token_hex(4)}"


class UnknownJob(KeyError):
    pass


class JobConflict(ValueError):
    pass


def scene_label(spec: JobSpec) -> str:
    return getattr(spec.scene, "builtin", None) or ("xml" if hasattr(spec.scene, "xml") else "path")


class JobService:
    def __init__(self, root: str | Path, queue: JobQueue, events: EventBus | None = None):
        self.root = Path(root)
        self.root.mkdir(parents=True, exist_ok=True)
        self.queue = queue
        self.events = events

    def _event(self, folder: JobFolder, event: dict) -> None:
        stored = folder.append_event(event)
        if self.events is not None:
            self.events.publish(folder.root.name, stored)

    # ------------------------------------------------------------------ paths

    def folder(self, job_id: str) -> JobFolder:
        if not JOB_ID.match(job_id or ""):
            raise UnknownJob(job_id)
        folder = JobFolder(self.root / job_id)
        if not folder.record_path.is_file():
            raise UnknownJob(job_id)
        return folder

    def _idempotency_path(self, key: str) -> Path:
        return self.root / ".idempotency" / hashlib.sha256(key.encode()).hexdigest()

    # ------------------------------------------------------------------ submit

    def find_idempotent(self, key: str) -> str | None:
        """The job an ``Idempotency-Key`` created, if any."""
        claim = self._idempotency_path(key)
        return self._await_claim(claim) if claim.is_file() else None

    def submit(self, spec: JobSpec, idempotency_key: str | None = None, fingerprint: str | None = None) -> tuple[str, bool]:
        """Create and enqueue a job; returns ``(id, created)``. With an ``idempotency_key`` that was
        seen before, returns the earlier job instead (``created`` False)."""
        claim = None
        if idempotency_key:
            claim = self._idempotency_path(idempotency_key)
            claim.parent.mkdir(parents=True, exist_ok=True)
            try:
                fd = os.open(claim, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                return self._await_claim(claim), False
            os.close(fd)
        job_id = new_job_id()
        folder = JobFolder(self.root / job_id)
        folder.root.mkdir(parents=True)
        folder.write("spec.json", spec.model_dump(mode="json"))
        now = now_iso()
        folder.write("record.json", {
            "id": job_id, "name": spec.name, "status": "queued", "method": spec.method, "scene": scene_label(spec),
            "created": now, "updated": now, "iteration": None, "iterations": spec.iterations, "attempts": 0,
            "error": None, "field": None, "idempotency_key": idempotency_key, "fingerprint": fingerprint,
        })
        self._event(folder, {"type": "status", "status": "queued"})
        if claim is not None:
            atomic_write_bytes(claim, job_id.encode())
        self.queue.enqueue(job_id)
        log.info("job %s queued (%s on %s)", job_id, spec.method, scene_label(spec))
        return job_id, True

    def _await_claim(self, claim: Path, timeout: float = 10.0) -> str:
        """The job id of an idempotency key (its creator may still be writing it)."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            text = claim.read_text().strip()
            if JOB_ID.match(text):
                return text
            time.sleep(0.02)
        raise JobConflict("a request with this Idempotency-Key is still being processed")

    # ------------------------------------------------------------------- read

    def record(self, job_id: str) -> dict:
        return self.folder(job_id).read("record.json")

    def ids(self) -> list[str]:
        """All job ids, newest first."""
        return sorted((p.name for p in self.root.iterdir() if JOB_ID.match(p.name) and (p / "record.json").is_file()),
                      reverse=True)

    def records(self, status: str | None = None) -> Iterator[dict]:
        for job_id in self.ids():
            try:
                record = self.record(job_id)
            except (UnknownJob, ValueError):
                continue
            if status is None or record.get("status") == status:
                yield record

    # ----------------------------------------------------------------- cancel

    def cancel(self, job_id: str) -> dict:
        """Ask a job to stop. A queued job is canceled at once; a running one stops at its next
        iteration boundary and keeps its artifacts. A finished job is a conflict."""
        folder = self.folder(job_id)
        record = folder.read("record.json")
        if record["status"] in FINISHED:
            raise JobConflict(f"job {job_id} is already {record['status']}")
        atomic_write_bytes(folder.root / "cancel-requested", now_iso().encode())
        if record["status"] == "queued":
            record.update(status="canceled", updated=now_iso())
            folder.write("record.json", record)
            self._event(folder, {"type": "status", "status": "canceled"})
        return folder.read("record.json")

    @staticmethod
    def cancel_requested(folder: JobFolder) -> bool:
        return (folder.root / "cancel-requested").is_file()

    # -------------------------------------------------------------- reconcile

    def reconcile(self, min_age_seconds: float = 5.0) -> list[str]:
        """Re-enqueue every unfinished job the queue does not hold (after Redis lost its data).
        Jobs changed in the last ``min_age_seconds`` are left alone: a job being submitted is in
        the store a moment before it is in the queue."""
        from datetime import datetime, timedelta, timezone

        queued = self.queue.queued_ids()
        cutoff = (datetime.now(timezone.utc) - timedelta(seconds=min_age_seconds)).isoformat(timespec="milliseconds")
        missing = [r["id"] for r in self.records()
                   if r.get("status") not in FINISHED and r["id"] not in queued and r.get("updated", "") < cutoff]
        for job_id in missing:
            self.queue.enqueue(job_id)
            log.warning("reconciler: re-enqueued unfinished job %s", job_id)
        return missing

    def delete(self, job_id: str) -> None:
        shutil.rmtree(self.folder(job_id).root)

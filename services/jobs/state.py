"""The one owner of a job's state.

Every change of a job's record (``record.json``: status, attempt, progress, error) goes through
:meth:`JobStates.transition`, a compare-and-set on the store (``put_if`` with the version read),
retried on contention. It checks, in one step with the write:

* the **fence**: with ``fence=<attempt>``, the record must still name that attempt, else :class:`Fenced`
  (another worker took the job over; the stale attempt must stop without writing);
* the **expected status**: with ``expect=``, the record's status must be one of them, else
  :class:`Conflict` (canceling a finished job, finishing a canceled one);

then appends the status event to the job's log and publishes it on the event bus. The loop and
the workers report outcomes; only this module writes records.
"""

from __future__ import annotations

import logging
from collections.abc import Collection
from datetime import UTC, datetime

from schemas.records import JobRecord, JobStatus
from services.queue.base import EventBus
from services.store.base import ArtifactStore
from services.store.job import JobFiles

log = logging.getLogger(__name__)


def now_iso() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


_ANY = object()


class UnknownJob(KeyError):
    """No job with this id (or not one the caller may see)."""


class Fenced(Exception):
    """This attempt no longer owns the job: stop without writing."""

    def __init__(self, job_id: str, attempt: str | None, owner: str | None):
        super().__init__(f"attempt {attempt} of job {job_id} was fenced off (the job now belongs to {owner})")
        self.attempt, self.owner = attempt, owner


class Conflict(Exception):
    """The job's status is not one this change applies to."""

    def __init__(self, message: str, record: JobRecord | None = None):
        super().__init__(message)
        self.record = record


class JobStates:
    """Reads and compare-and-set writes of job records, with their status events."""

    def __init__(self, store: ArtifactStore, events: EventBus | None = None, retries: int = 50):
        self.store = store
        self.events = events
        self.retries = retries

    def files(self, job_id: str) -> JobFiles:
        return JobFiles(self.store, job_id)

    # -------------------------------------------------------------------- reads

    def get(self, job_id: str) -> JobRecord:
        data = self.store.get(self.files(job_id).key(JobFiles.RECORD))
        if data is None:
            raise UnknownJob(job_id)
        return JobRecord.model_validate_json(data)

    # ------------------------------------------------------------------- writes

    def create(self, record: JobRecord) -> JobRecord:
        """Store a new job's record (fails if the id exists) and its first event."""
        key = self.files(record.id).key(JobFiles.RECORD)
        if self.store.put_if(key, _encode(record), None) is None:
            raise Conflict(f"job {record.id} already exists")
        self.event(record.id, {"type": "status", "status": record.status.value})
        return record

    def transition(self, job_id: str, to: JobStatus | None = None, *, fence: str | None = None,
                   expect: Collection[JobStatus] | None = None, expect_attempt: object = _ANY,
                   note: str | None = None, **fields) -> JobRecord:
        """Change the record in one compare-and-set and return the new record.

        ``to``              the new status (None: only ``fields`` change)
        ``fence``           the record must name this attempt (:class:`Fenced` otherwise)
        ``expect``          the statuses this change applies to (:class:`Conflict` otherwise)
        ``expect_attempt``  the record must still name this attempt, None included (a claim:
                            :class:`Conflict` if another worker claimed the job meanwhile)
        ``note``            said in the status event
        ``fields``          other record fields to set (``iteration=``, ``error=``, ``attempt=``, ...)
        """
        key = self.files(job_id).key(JobFiles.RECORD)
        for _ in range(self.retries):
            got = self.store.get_versioned(key)
            if got is None:
                raise UnknownJob(job_id)
            before = JobRecord.model_validate_json(got[0])
            if fence is not None and before.attempt != fence:
                raise Fenced(job_id, fence, before.attempt)
            if expect is not None and before.status not in expect:
                raise Conflict(f"job {job_id} is {before.status.value}", before)
            if expect_attempt is not _ANY and before.attempt != expect_attempt:
                raise Conflict(f"job {job_id} was claimed by attempt {before.attempt}", before)
            now = now_iso()
            update = {**fields, "updated": now}
            if to is not None:
                update["status"] = to
                if to is JobStatus.RUNNING and before.started is None:
                    update["started"] = now
                if to.finished:
                    update["finished"] = now
            after = before.model_copy(update=update)
            if self.store.put_if(key, _encode(after), got[1]) is not None:
                break
        else:
            raise Conflict(f"job {job_id}: the record kept changing ({self.retries} attempts)")
        if (to is not None and to != before.status) or note:
            event = {"type": "status", "status": after.status.value}
            if after.error and after.status is JobStatus.FAILED:
                event["error"] = after.error
            if note:
                event["note"] = note
            writer = fence or fields.get("attempt")
            if writer:  # which attempt wrote it: the history shows one writer at a time
                event["attempt"] = writer
            self.event(job_id, event)
        log.debug("job %s: %s -> %s %s", job_id, before.status.value, after.status.value, sorted(fields))
        return after

    def event(self, job_id: str, event: dict, *, durable: bool = True) -> dict:
        """Append an event to the job's log and publish it (the store's copy is what readers
        replay); ``durable=False`` for per-iteration events (:meth:`ArtifactStore.put`)."""
        stored = self.store.append_event(self.files(job_id).prefix, event, durable=durable)
        if self.events is not None:
            self.events.publish(job_id, stored)
        return stored


def _encode(record: JobRecord) -> bytes:
    return (record.model_dump_json(indent=2) + "\n").encode()

"""The job service: submit, list, inspect, cancel and delete jobs, over the store and the queue.

The store is the source of truth; the queue only says which job a worker should pick up next.
The API, the workers and the CLI all go through this facade; a job's record changes only through
:class:`services.jobs.state.JobStates`. No Mitsuba and no torch here: the API starts without them.

Jobs belong to the key that created them (``owner``, a hash of the key): a caller sees only its
own jobs unless it is an admin; an id of someone else's job is :class:`UnknownJob` (a 404, which
does not tell that the id exists).
"""

from __future__ import annotations

import hashlib
import logging
import re
import secrets
import time
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

from schemas.job import JobSpec
from schemas.records import ACTIVE, FINISHED, JobRecord, JobStatus
from services.jobs.quotas import check_room
from services.jobs.state import Conflict, JobStates, UnknownJob, now_iso
from services.queue.base import EventBus, JobQueue, LockBusy
from services.settings import Limits
from services.store.base import ArtifactStore
from services.store.job import JobFiles

log = logging.getLogger(__name__)

JOB_ID = re.compile(r"^[0-9a-f]{20}$")
ANONYMOUS = "anonymous"
#: A key's stored bytes found under its quota are not summed again for this long (per process).
ROOM_SECONDS = 10.0
#: The longest a submission holds its key's lock (count, then create): a holder that died frees it then.
SUBMIT_LOCK_SECONDS = 60.0
#: A claim whose job never appeared (its writer died between the two steps) is stale after this.
CLAIM_STALE_SECONDS = 30.0


def new_job_id() -> str:
    """20 hex characters: milliseconds since the epoch (12) then randomness (8): sorts by time."""
    return f"{int(time.time() * 1000):012x}{secrets.token_hex(4)}"


def scene_label(spec: JobSpec) -> str:
    return getattr(spec.scene, "builtin", None) or ("xml" if hasattr(spec.scene, "xml") else "path")


@dataclass(frozen=True)
class Caller:
    """Who is asking: the owner id of their key, and whether the key is an admin's."""

    owner: str = ANONYMOUS
    admin: bool = False

    def may_see(self, record: JobRecord) -> bool:
        return self.admin or record.owner == self.owner


SYSTEM = Caller(ANONYMOUS, admin=True)  # workers, reconcilers, the CLI


class TooManyJobs(Exception):
    """The caller has too many active jobs (a 429)."""


class JobService:
    def __init__(self, store: ArtifactStore, queue: JobQueue, events: EventBus | None = None):
        self.store = store
        self.queue = queue
        self.events = events
        self.states = JobStates(store, events)
        self._room: dict[str, float] = {}   # owner -> when its stored bytes were last found under its quota

    # ------------------------------------------------------------------ reads

    def record(self, job_id: str, caller: Caller = SYSTEM) -> JobRecord:
        if not JOB_ID.match(job_id or ""):
            raise UnknownJob(job_id)
        record = self.states.get(job_id)
        if not caller.may_see(record):
            raise UnknownJob(job_id)
        return record

    def files(self, job_id: str, caller: Caller = SYSTEM) -> JobFiles:
        """The job's files, once the caller may see the job (:class:`UnknownJob` otherwise)."""
        self.record(job_id, caller)
        return self.states.files(job_id)

    def ids(self) -> list[str]:
        """All job ids, newest first."""
        return sorted((key[:-1] for key in self.store.keys("", delimiter=True)
                       if key.endswith("/") and JOB_ID.match(key[:-1])), reverse=True)

    def records(self, caller: Caller = SYSTEM, status: JobStatus | None = None,
                before: str | None = None) -> Iterator[JobRecord]:
        """Records the caller may see, newest first (ids below ``before`` only)."""
        for job_id in self.ids():
            if before is not None and job_id >= before:
                continue
            try:
                record = self.states.get(job_id)
            except (UnknownJob, ValueError):
                continue  # being created, or being deleted
            if caller.may_see(record) and (status is None or record.status == status):
                yield record

    # ----------------------------------------------------------------- submit

    def _claim_key(self, caller: Caller, key: str) -> str:
        return f".idempotency/{caller.owner}/{hashlib.sha256(key.encode()).hexdigest()}"

    def find_idempotent(self, caller: Caller, key: str) -> JobRecord | None:
        """The job a caller's ``Idempotency-Key`` created, if any (keys are scoped per caller)."""
        got = self.store.get(self._claim_key(caller, key))
        if got is None:
            return None
        try:
            return self.record(got.decode().strip(), caller)
        except UnknownJob:
            return None

    def submit(self, spec: JobSpec, caller: Caller = SYSTEM, idempotency_key: str | None = None,
               max_active: int | None = None, limits: Limits | None = None, **extra) -> tuple[JobRecord, bool]:
        """Create and enqueue a job; returns ``(record, created)``. With an ``idempotency_key`` the
        caller used before, returns that job instead (``created`` False). ``extra`` are further
        record fields (an experiment's id and varied values). With ``limits``, a key whose files
        reached ``key_bytes`` is refused (:class:`~services.jobs.quotas.StorageQuota`)."""
        if limits is not None:
            self._check_room(caller.owner, limits)
        job_id = new_job_id()
        if idempotency_key:
            existing = self._claim(caller, idempotency_key, job_id)
            if existing is not None:
                return existing, False
        if max_active is None:
            return self._create(job_id, spec, caller, idempotency_key, extra), True
        # the count and the creation are one step under the key's lock (every API process and
        # scheduler shares it): concurrent submissions cannot both take the last place
        try:
            with self.queue.hold(f"active:{caller.owner}", seconds=SUBMIT_LOCK_SECONDS):
                active = self.active_count(caller.owner)
                if active >= max_active:
                    raise TooManyJobs(f"{active} jobs of this key are queued or running (limit {max_active}, "
                                      f"NDRF_MAX_ACTIVE_JOBS_PER_KEY)")
                return self._create(job_id, spec, caller, idempotency_key, extra), True
        except LockBusy:
            raise TooManyJobs("other submissions of this key are being counted: retry") from None

    def _check_room(self, owner: str, limits: Limits) -> None:
        """The key's stored bytes against its quota, summed from the store at most every
        ``ROOM_SECONDS`` per key (each attempt checks again when it starts)."""
        now = time.monotonic()
        seen = self._room.get(owner)
        if seen is not None and now - seen < ROOM_SECONDS:
            return
        check_room(self.states, owner, limits)
        self._room[owner] = now

    def active_count(self, owner: str) -> int:
        """Queued or running jobs of ``owner``."""
        return sum(1 for r in self.records() if r.owner == owner and r.status in ACTIVE)

    def _create(self, job_id: str, spec: JobSpec, caller: Caller, idempotency_key: str | None,
                extra: dict) -> JobRecord:
        files = self.states.files(job_id)
        files.write(JobFiles.SPEC, spec.model_dump(mode="json"))
        now = now_iso()
        record = JobRecord(id=job_id, name=spec.name, owner=caller.owner, status=JobStatus.QUEUED,
                           method=str(spec.method), scene=scene_label(spec), created=now, updated=now,
                           iterations=spec.iterations, idempotency_key=idempotency_key,
                           fingerprint=spec.fingerprint(), **extra)
        self.states.create(record)
        self.queue.enqueue(job_id, owner=caller.owner)
        log.info("job %s queued (%s on %s)", job_id, spec.method, record.scene)
        return record

    def _claim(self, caller: Caller, key: str, job_id: str) -> JobRecord | None:
        """Claim an idempotency key for ``job_id`` in one atomic create (content included);
        returns the job an earlier claim names, if any. A claim whose job never appeared (its
        writer died) is taken over once stale."""
        claim = self._claim_key(caller, key)
        if self.store.put_if(claim, job_id.encode(), None) is not None:
            return None
        got = self.store.get_versioned(claim)
        if got is None:
            return self._claim(caller, key, job_id)
        earlier = got[0].decode().strip()
        try:
            return self.record(earlier, caller)
        except UnknownJob:
            created = int(earlier[:12], 16) / 1000 if JOB_ID.match(earlier) else 0.0
            if time.time() - created < CLAIM_STALE_SECONDS:
                raise Conflict("a request with this Idempotency-Key is still being processed") from None
            if self.store.put_if(claim, job_id.encode(), got[1]) is None:
                raise Conflict("a request with this Idempotency-Key is being processed") from None
            return None

    # ----------------------------------------------------------------- cancel

    def cancel(self, job_id: str, caller: Caller = SYSTEM) -> JobRecord:
        """Ask a job to stop. A queued job is canceled at once; a running one stops at its next
        training step and keeps its artifacts. A finished job is a :class:`Conflict`."""
        record = self.record(job_id, caller)
        if record.status in FINISHED:
            raise Conflict(f"job {job_id} is already {record.status.value}", record)
        try:
            canceled = self.states.transition(job_id, JobStatus.CANCELED, expect={JobStatus.QUEUED},
                                              cancel_requested=True)
        except Conflict:  # running (or it just started): its runner stops it
            return self.states.transition(job_id, expect={JobStatus.RUNNING}, cancel_requested=True)
        self.queue.withdraw(job_id, record.owner)   # no worker picks it up, its owner's turn is not spent
        return canceled

    def request_images(self, job_id: str, caller: Caller = SYSTEM) -> JobRecord:
        """Ask a running job to write the renders of every view and its gradient images at its
        next iteration, whatever its images schedule (the dashboard's button). Only a running job
        has a next iteration: anything else is a :class:`Conflict`."""
        self.record(job_id, caller)
        try:
            return self.states.transition(job_id, expect={JobStatus.RUNNING}, images_requested=True)
        except Conflict as exc:
            raise Conflict(f"job {job_id} is not running: it has no next iteration to write images at",
                           exc.record) from None

    def cancel_requested(self, job_id: str) -> bool:
        return self.states.get(job_id).cancel_requested

    # ----------------------------------------------------------------- delete

    def delete(self, job_id: str, caller: Caller = SYSTEM) -> None:
        """Delete a finished job and all its files (an active job must be canceled first)."""
        record = self.record(job_id, caller)
        if record.status not in FINISHED:
            raise Conflict(f"job {job_id} is {record.status.value}: cancel it first", record)
        self.store.delete_prefix(f"{job_id}/")
        self._forget_claim(record)
        log.info("deleted job %s", job_id)

    def _forget_claim(self, record: JobRecord) -> None:
        """Delete the idempotency claim of a deleted job (a retry with its key then makes a new job)."""
        if record.idempotency_key:
            self.store.delete_prefix(self._claim_key(Caller(record.owner), record.idempotency_key))

    def sweep(self, retention_days: float) -> list[str]:
        """Delete finished jobs last changed more than ``retention_days`` ago."""
        cutoff = (datetime.now(UTC) - timedelta(days=retention_days)).isoformat(timespec="milliseconds")
        old = [r for r in self.records() if r.status in FINISHED and r.updated < cutoff]
        gone = [r.id for r in old]
        for record in old:
            self.store.delete_prefix(f"{record.id}/")
            self._forget_claim(record)
        if gone:
            log.info("retention: deleted %d finished job(s) older than %g days", len(gone), retention_days)
        return gone

    # -------------------------------------------------------------- reconcile

    def reconcile(self, grace_seconds: float) -> list[str]:
        """Re-enqueue the unfinished jobs the queue lost (Redis restarted without persistence).

        A job is a candidate when the queue holds no marker of it and, if it is running, the
        attempt its record names has no live heartbeat. It is re-enqueued only once it has been a
        candidate for ``grace_seconds`` (across reconciler passes, whichever process runs them): a
        live attempt re-registers itself at its next lease renewal after Redis comes back, and a
        job being submitted is in the store a moment before it is in the queue. The enqueue itself
        is a no-op if the job got a marker or its attempt a heartbeat meanwhile."""
        held = self.queue.queued_ids()
        candidates: dict[str, JobRecord] = {}
        for record in self.records():
            if record.status not in ACTIVE or record.id in held:
                continue
            if record.status is JobStatus.RUNNING and record.attempt and self.queue.alive(record.id, record.attempt):
                continue
            candidates[record.id] = record
        added = []
        for job_id in sorted(self.queue.orphans(candidates, grace_seconds)):
            record = candidates[job_id]
            attempt = record.attempt if record.status is JobStatus.RUNNING else None
            if self.queue.enqueue(job_id, unless_alive=attempt, owner=record.owner):
                added.append(job_id)
                log.warning("reconciler: re-enqueued unfinished job %s (%s, attempt %s)", job_id,
                            record.status.value, record.attempt)
        return added

"""A key's use of the service against its quotas (issue 38): stored bytes, active and running
jobs. The store is the source of truth for bytes and jobs; the queue for what runs now.

Stored bytes are checked at two places: a submission of a key at ``NDRF_MAX_KEY_BYTES`` is
refused (a 507), and an attempt gets as its disk budget the smaller of ``NDRF_MAX_JOB_BYTES`` and
what the key has left (its other jobs' files counted when the attempt starts), so a running job
stops with a failure naming the key's quota before it would pass it. Nothing already written is
touched. Two jobs of one key that start together each get what was left then: the key can pass its
quota by at most ``NDRF_MAX_RUNNING_JOBS_PER_KEY - 1`` such shares, never without bound.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass

from schemas.records import ACTIVE, JobRecord, JobStatus
from services.jobs.state import JobStates, UnknownJob
from services.settings import Limits

log = logging.getLogger(__name__)

_JOB = re.compile(r"^[0-9a-f]{20}$")


class StorageQuota(Exception):
    """The key's stored files reached ``NDRF_MAX_KEY_BYTES`` (a 507)."""


@dataclass(frozen=True)
class Budget:
    """An attempt's disk budget and the limit that sets it."""

    bytes: int
    limit: str


def owner_records(states: JobStates, owner: str) -> list[JobRecord]:
    out = []
    for key in states.store.keys("", delimiter=True):
        if not (key.endswith("/") and _JOB.match(key[:-1])):
            continue
        try:
            record = states.get(key[:-1])
        except (UnknownJob, ValueError):
            continue
        if record.owner == owner:
            out.append(record)
    return out


def stored_bytes(states: JobStates, records: list[JobRecord], skip: str | None = None) -> int:
    """Bytes of the files of ``records`` (but ``skip``)."""
    return sum(states.store.prefix_bytes(f"{r.id}/") for r in records if r.id != skip)


def check_room(states: JobStates, owner: str, limits: Limits) -> None:
    """Raise :class:`StorageQuota` when the key's files already take ``key_bytes``."""
    used = stored_bytes(states, owner_records(states, owner))
    if used >= limits.key_bytes:
        raise StorageQuota(f"this key's stored files take {used >> 20} MiB, its quota is {limits.key_bytes >> 20} "
                           f"MiB (NDRF_MAX_KEY_BYTES): delete finished jobs to make room")


def attempt_budget(states: JobStates, job_id: str, limits: Limits) -> Budget:
    """The disk budget of an attempt of ``job_id``: its own cap, or what its key has left."""
    owner = states.get(job_id).owner
    others = stored_bytes(states, owner_records(states, owner), skip=job_id)
    left = max(0, limits.key_bytes - others)
    if left < limits.job_bytes:
        log.info("job %s: its key has %d MiB of its quota left", job_id, left >> 20)
        return Budget(left, f"NDRF_MAX_KEY_BYTES: the key's other files take {others >> 20} MiB of "
                            f"{limits.key_bytes >> 20} MiB")
    return Budget(limits.job_bytes, "NDRF_MAX_JOB_BYTES")


@dataclass(frozen=True)
class Use:
    stored_bytes: int
    active_jobs: int
    running_jobs: int


def key_use(states: JobStates, owner: str) -> Use:
    records = owner_records(states, owner)
    return Use(stored_bytes(states, records), sum(1 for r in records if r.status in ACTIVE),
               sum(1 for r in records if r.status is JobStatus.RUNNING))

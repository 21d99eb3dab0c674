"""The one writer of experiment records, as :mod:`services.jobs.state` is for jobs.

Store layout (any :class:`~services.store.base.ArtifactStore`, folder or object store)::

    experiments/<id>/experiment.json   ExperimentRecord: sweep, runs and their jobs, status
    experiments/<id>/base.json         the base job (written once; it may carry a whole scene)
    experiments/<id>/events.jsonl      append-only event log (status, run changes), for SSE
    experiments/<id>/metrics/<job>.json  derived metrics of a finished run's job (a cache)
    experiments-active/<id>            marker: the scheduler looks at this experiment; its content
                                       changes with every change of the record (the scheduler
                                       reads again only an experiment whose marker changed)

Every change is a compare-and-set (``put_if`` on the version read), retried on contention, so
two schedulers, or a scheduler and an API process handling a cancel, never lose each other's
update; that, not the scheduler's lock, is what keeps ``max_concurrent`` exact.
"""

from __future__ import annotations

import logging
import re
import secrets
import time
from collections.abc import Callable, Iterator
from typing import Any

from schemas.experiments import RUN_ACTIVE, RUN_FINISHED, ExperimentRecord, ExperimentStatus
from services.jobs.state import now_iso
from services.queue.base import EventBus
from services.store.base import ArtifactStore

log = logging.getLogger(__name__)

EXPERIMENT_ID = re.compile(r"^e[0-9a-f]{20}$")
ROOT, ACTIVE = "experiments/", "experiments-active/"


def new_experiment_id() -> str:
    """'e' + 20 hex characters: milliseconds since the epoch then randomness (sorts by time)."""
    return f"e{int(time.time() * 1000):012x}{secrets.token_hex(4)}"


class UnknownExperiment(KeyError):
    """No experiment with this id (or not one the caller may see)."""


class ExperimentConflict(Exception):
    """The change does not apply (nothing to retry, the record kept changing)."""


class ExperimentStates:
    def __init__(self, store: ArtifactStore, events: EventBus | None = None, retries: int = 50):
        self.store, self.events, self.retries = store, events, retries

    @staticmethod
    def prefix(exp_id: str) -> str:
        return f"{ROOT}{exp_id}/"

    def _record_key(self, exp_id: str) -> str:
        return self.prefix(exp_id) + "experiment.json"

    # -------------------------------------------------------------------- reads

    def get(self, exp_id: str) -> ExperimentRecord:
        if not EXPERIMENT_ID.match(exp_id or ""):
            raise UnknownExperiment(exp_id)
        data = self.store.get(self._record_key(exp_id))
        if data is None:
            raise UnknownExperiment(exp_id)
        return ExperimentRecord.model_validate_json(data)

    def base(self, exp_id: str) -> dict:
        return self.store.get_json(self.prefix(exp_id) + "base.json")

    def ids(self) -> list[str]:
        """Every experiment id, newest first."""
        return sorted((key[len(ROOT):-1] for key in self.store.keys(ROOT, delimiter=True)
                       if key.endswith("/") and EXPERIMENT_ID.match(key[len(ROOT):-1])), reverse=True)

    def active_ids(self) -> list[str]:
        return sorted(key[len(ACTIVE):] for key in self.store.keys(ACTIVE, delimiter=True)
                      if EXPERIMENT_ID.match(key[len(ACTIVE):]))

    def active_marks(self) -> dict[str, bytes]:
        """The active experiments and their markers' content, which every change of a record
        changes (:meth:`update` writes the marker after the record): a reader that saw a marker
        before reading the record sees a different one after any later change."""
        marks = {}
        for exp_id in self.active_ids():
            mark = self.store.get(ACTIVE + exp_id)
            if mark is not None:
                marks[exp_id] = mark
        return marks

    # ------------------------------------------------------------------- writes

    def create(self, record: ExperimentRecord, base: dict) -> ExperimentRecord:
        prefix = self.prefix(record.id)
        self.store.put_json(prefix + "base.json", base)
        if self.store.put_if(self._record_key(record.id), _encode(record), None) is None:
            raise ExperimentConflict(f"experiment {record.id} already exists")
        self.mark_active(record.id)
        self.event(record.id, {"type": "status", "status": record.status.value, "runs": len(record.runs)})
        return record

    def update(self, exp_id: str, change: Callable[[ExperimentRecord], ExperimentRecord | None],
               events: list[dict] | None = None) -> tuple[ExperimentRecord, bool]:
        """Apply ``change`` (a function of a fresh copy of the record, returning the new record or
        None for "no change") in one compare-and-set, retried on contention. ``change`` may run
        several times and must have no other effect than filling ``events`` (cleared before each
        attempt): they are appended once the write succeeded, before the status event the write
        may cause. Returns ``(record, changed)``."""
        key = self._record_key(exp_id)
        for _ in range(self.retries):
            got = self.store.get_versioned(key)
            if got is None:
                raise UnknownExperiment(exp_id)
            before = ExperimentRecord.model_validate_json(got[0])
            if events is not None:
                events.clear()
            after = change(before.model_copy(deep=True))
            if after is None:
                return before, False
            after.updated = now_iso()
            after.status = derive_status(after)
            if after.status.finished and before.status != after.status:
                after.finished = after.updated
            elif not after.status.finished:
                after.finished = None
            if self.store.put_if(key, _encode(after), got[1]) is not None:
                break
        else:
            raise ExperimentConflict(f"experiment {exp_id}: the record kept changing ({self.retries} attempts)")
        if not after.status.finished or not before.status.finished:
            self.mark_active(exp_id)   # a new marker: the scheduler reads this record again
        for event in events or ():
            self.event(exp_id, event)
        if after.status != before.status:
            self.event(exp_id, {"type": "status", "status": after.status.value, "counts": counts(after)})
        return after, True

    def event(self, exp_id: str, event: dict[str, Any]) -> dict:
        stored = self.store.append_event(self.prefix(exp_id), event)
        if self.events is not None:
            self.events.publish(exp_id, stored)
        return stored

    def read_events(self, exp_id: str, after: int = 0, cursor: Any = None) -> tuple[list[dict], Any]:
        return self.store.read_events(self.prefix(exp_id), after, cursor)

    # ------------------------------------------------------------------ markers

    def mark_active(self, exp_id: str) -> None:
        """Mark the experiment for the scheduler, with a marker unlike any it had."""
        self.store.put(ACTIVE + exp_id, f"{time.time_ns()} {secrets.token_hex(4)}\n".encode())

    def unmark_active(self, exp_id: str) -> None:
        self.store.delete_prefix(ACTIVE + exp_id)

    # ------------------------------------------------------------------ metrics

    def cached_metrics(self, exp_id: str, job_id: str) -> dict | None:
        return self.store.get_json(f"{self.prefix(exp_id)}metrics/{job_id}.json")

    def cache_metrics(self, exp_id: str, job_id: str, metrics: dict) -> None:
        self.store.put_json(f"{self.prefix(exp_id)}metrics/{job_id}.json", metrics)

    def records(self) -> Iterator[ExperimentRecord]:
        for exp_id in self.ids():
            try:
                yield self.get(exp_id)
            except (UnknownExperiment, ValueError):
                continue


def counts(record: ExperimentRecord) -> dict[str, int]:
    """Runs by status."""
    out: dict[str, int] = {}
    for run in record.runs:
        out[run.status] = out.get(run.status, 0) + 1
    return out


def derive_status(record: ExperimentRecord) -> ExperimentStatus:
    """The experiment's status from its runs: running while any run is pending, being admitted,
    queued or running (queued if none has started yet); then canceled (by its owner, or a run
    was), failed (a run failed) or succeeded."""
    statuses = [run.status for run in record.runs]
    if any(s in RUN_ACTIVE or s == "pending" for s in statuses):
        started = any(s == "running" or s in RUN_FINISHED for s in statuses)
        return ExperimentStatus.RUNNING if started else ExperimentStatus.QUEUED
    if record.canceled or "canceled" in statuses:
        return ExperimentStatus.CANCELED
    if "failed" in statuses:
        return ExperimentStatus.FAILED
    return ExperimentStatus.SUCCEEDED


def _encode(record: ExperimentRecord) -> bytes:
    return (record.model_dump_json(indent=1) + "\n").encode()

"""The artifact store interface: the source of truth of every job (records, specs, iterations,
images, checkpoints, the event log) and of every experiment.

Two implementations: a folder (:mod:`services.store.local`, the embedded default) and an
S3-compatible bucket (:mod:`services.store.s3`). Keys are ``/``-separated relative paths
(``<job>/iterations/000003/record.json``). What every implementation guarantees:

* ``put`` is atomic: a reader sees the old object or the new one, never a torn one;
* ``put_if`` is a compare-and-set: it writes only if the object's version is still ``version``
  (or, with ``version=None``, only if the object does not exist), so two writers on two
  machines cannot both win (the fenced job-record update, the idempotency claim);
* the event log of a prefix is append-only with consecutive sequence numbers from 1, and
  ``read_events`` returns complete events only.
"""

from __future__ import annotations

import json
from abc import ABC, abstractmethod
from collections.abc import Iterator
from pathlib import Path
from typing import Any, BinaryIO


class StoreFull(OSError):
    """A write was refused for lack of space (disk full, quota): the job that wrote it fails
    with this message; the worker goes on."""


class ArtifactStore(ABC):
    """Objects by key, compare-and-set, and append-only event logs."""

    # ------------------------------------------------------------------ objects

    @abstractmethod
    def get(self, key: str) -> bytes | None:
        """The object's bytes, or None if it does not exist."""

    @abstractmethod
    def put(self, key: str, data: bytes, *, durable: bool = True) -> None:
        """Write the whole object atomically. ``durable=False``: it need not survive a power loss
        until the next :meth:`flush` (a job's per-iteration files, made durable at checkpoints)."""

    def put_file(self, key: str, handle: BinaryIO, size: int) -> None:
        """Write the object from the first ``size`` bytes of the open file ``handle`` (a view's
        files, written by a sandboxed child), atomically as :meth:`put`. The folder and S3 stores
        copy it in chunks, never the whole file in memory; this default reads it whole."""
        self.put(key, handle.read(size))

    @abstractmethod
    def get_versioned(self, key: str) -> tuple[bytes, str] | None:
        """The object and an opaque version (an ETag), or None."""

    @abstractmethod
    def put_if(self, key: str, data: bytes, version: str | None) -> str | None:
        """Write only if the object's version is ``version`` (None: only if it does not exist).
        Returns the new version, or None when the condition failed (nothing was written)."""

    @abstractmethod
    def exists(self, key: str) -> bool: ...

    @abstractmethod
    def size(self, key: str) -> int | None:
        """Bytes of the object, or None if it does not exist."""

    @abstractmethod
    def keys(self, prefix: str, *, delimiter: bool = False) -> Iterator[str]:
        """Keys under ``prefix`` in lexicographic order. With ``delimiter``, only the immediate
        children: object keys and sub-prefixes (ending in ``/``)."""

    @abstractmethod
    def delete_prefix(self, prefix: str) -> int:
        """Delete every object under ``prefix``; returns how many bytes were freed."""

    @abstractmethod
    def open(self, key: str) -> BinaryIO | None:
        """A readable binary stream of the object (large files are not read into memory)."""

    def local_path(self, key: str) -> Path | None:
        """A path on this machine holding the object, when the store is a folder (None otherwise)."""
        return None

    def redirect_url(self, key: str) -> str | None:
        """A short-lived URL a client may fetch the object from directly (a pre-signed S3 URL),
        when the store is configured to hand large objects out that way; None otherwise."""
        return None

    def get_range(self, key: str, start: int, length: int) -> bytes | None:
        """``length`` bytes of the object from ``start`` (fewer at its end), or None if it does not
        exist: one slice of a large array without reading the rest."""
        handle = self.open(key)
        if handle is None:
            return None
        with handle:
            handle.seek(start)
            return handle.read(length)

    def prefix_bytes(self, prefix: str) -> int:
        """Bytes of the objects under ``prefix`` (a store that lists sizes overrides this)."""
        return sum(self.size(key) or 0 for key in self.keys(prefix))

    @abstractmethod
    def usage_bytes(self) -> int:
        """Bytes stored in total (for /metrics; may be computed lazily and cached)."""

    # ------------------------------------------------------------------- events

    @abstractmethod
    def append_event(self, prefix: str, event: dict, *, durable: bool = True) -> dict:
        """Append ``event`` to the log of ``prefix`` with the next sequence number (``seq``) and
        the time (``time``) added; returns the stored event. Safe against concurrent appenders.
        ``durable=False``: as for :meth:`put`."""

    def flush(self) -> None:  # noqa: B027 (a hook with a default, not an abstract method)
        """Make every write done with ``durable=False`` so far durable (no-op where every write
        already is, as in S3)."""

    @abstractmethod
    def read_events(self, prefix: str, after: int = 0, cursor: Any = None) -> tuple[list[dict], Any]:
        """Complete events with ``seq > after``, in order, and a cursor that makes the next call
        with it read only what was appended since (``None`` for a fresh read)."""

    # --------------------------------------------------------------- JSON sugar

    def get_json(self, key: str, default: Any = None) -> Any:
        data = self.get(key)
        return default if data is None else json.loads(data)

    def put_json(self, key: str, value: Any) -> None:
        from services.store.files import dumps

        self.put(key, (dumps(value) + "\n").encode())

    def close(self) -> None:  # noqa: B027 (a hook with a default, not an abstract method)
        """Release connections (no-op for folders)."""

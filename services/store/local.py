"""The folder store: the embedded default (``NDRF_STORE=./runs``), and what several processes of
one machine (or a compose file's shared volume) share.

* ``put``: temporary file in the same folder, fsync, ``os.replace`` (atomic on POSIX); with
  ``durable=False`` the fsync is left to :meth:`FolderStore.flush` (a job's per-iteration record
  and event: the writer flushes before every checkpoint, so what a resume relies on is durable,
  and an iteration costs no fsync; a process crash loses nothing, only a power loss could lose
  the iterations after the last checkpoint, which a resume recomputes anyway);
* ``put_if``: an exclusive ``flock`` on a lock file beside the object, then compare the content
  hash (the version, like an S3 ETag) and ``put``. flock is per machine: across machines use the
  S3 store (NFS rename and lock semantics differ);
* event logs: ``<prefix>events.jsonl``, one JSON object per line, appended under ``flock`` with
  ``O_APPEND`` and fsync; a reader keeps its byte offset as the cursor and skips a torn last line.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import hashlib
import json
import os
import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from datetime import UTC
from pathlib import Path
from typing import Any, BinaryIO

from services.store.base import ArtifactStore, StoreFull
from services.store.files import atomic_copy, atomic_write_bytes, dumps

EVENTS = "events.jsonl"


def version_of(data: bytes) -> str:
    return hashlib.blake2b(data, digest_size=12).hexdigest()


def now_iso() -> str:
    from datetime import datetime

    return datetime.now(UTC).isoformat(timespec="milliseconds")


class FolderStore(ArtifactStore):
    def __init__(self, root: str | Path, usage_ttl: float = 60.0):
        self.root = Path(root).resolve()
        self.root.mkdir(parents=True, exist_ok=True)
        self._usage: tuple[float, int] | None = None
        self._usage_ttl = usage_ttl
        self._unflushed: set[Path] = set()

    def __repr__(self) -> str:
        return f"FolderStore({str(self.root)!r})"

    def path(self, key: str) -> Path:
        parts = key.split("/")
        if key.startswith("/") or ".." in parts or "\\" in key:
            raise ValueError(f"store key {key!r} must be a relative path without '..'")
        return self.root.joinpath(*[p for p in parts if p])

    # ------------------------------------------------------------------ objects

    def get(self, key: str) -> bytes | None:
        try:
            return self.path(key).read_bytes()
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            return None

    def put(self, key: str, data: bytes, *, durable: bool = True) -> None:
        try:
            path = atomic_write_bytes(self.path(key), data, sync=durable)
        except OSError as exc:
            raise _translated(exc, key) from exc
        if not durable:
            self._unflushed.add(path)

    def put_file(self, key: str, handle: BinaryIO, size: int) -> None:
        try:
            atomic_copy(self.path(key), handle, size)
        except OSError as exc:
            raise _translated(exc, key) from exc

    def flush(self) -> None:
        pending, self._unflushed = self._unflushed, set()
        for path in sorted(pending):
            with contextlib.suppress(FileNotFoundError):   # deleted meanwhile
                fd = os.open(path, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)
        for folder in sorted({p.parent for p in pending}):   # the renames themselves
            with contextlib.suppress(FileNotFoundError):
                fd = os.open(folder, os.O_RDONLY)
                try:
                    os.fsync(fd)
                finally:
                    os.close(fd)

    def get_versioned(self, key: str) -> tuple[bytes, str] | None:
        data = self.get(key)
        return None if data is None else (data, version_of(data))

    def put_if(self, key: str, data: bytes, version: str | None) -> str | None:
        with self._locked(key):
            current = self.get(key)
            if (current is None) != (version is None) or (current is not None and version_of(current) != version):
                return None
            self.put(key, data)
        return version_of(data)

    def exists(self, key: str) -> bool:
        return self.path(key).is_file()

    def size(self, key: str) -> int | None:
        try:
            return self.path(key).stat().st_size
        except (FileNotFoundError, NotADirectoryError):
            return None

    def keys(self, prefix: str, *, delimiter: bool = False) -> Iterator[str]:
        folder, _, partial = prefix.rpartition("/")
        base = self.path(folder) if folder else self.root
        head = f"{folder}/" if folder else ""
        if not base.is_dir():
            return
        if delimiter:
            entries = [e for e in os.scandir(base) if not e.name.startswith(".") and e.name.startswith(partial)]
            yield from sorted(head + e.name + ("/" if e.is_dir() else "") for e in entries)
            return
        keys = []
        for dirpath, dirnames, filenames in os.walk(base):
            dirnames[:] = [d for d in dirnames if not d.startswith(".")]
            rel = Path(dirpath).relative_to(self.root).as_posix()
            keys += [name if rel == "." else f"{rel}/{name}" for name in filenames if not name.startswith(".")]
        yield from sorted(k for k in keys if k.startswith(prefix))

    def delete_prefix(self, prefix: str) -> int:
        target = self.path(prefix)
        if target.is_file():
            size = target.stat().st_size
            target.unlink()
            return size
        if not target.is_dir():
            return 0
        size = sum(p.stat().st_size for p in target.rglob("*") if p.is_file())
        shutil.rmtree(target, ignore_errors=True)
        self._usage = None
        return size

    def open(self, key: str) -> BinaryIO | None:
        try:
            return self.path(key).open("rb")
        except (FileNotFoundError, NotADirectoryError, IsADirectoryError):
            return None

    def local_path(self, key: str) -> Path | None:
        path = self.path(key)
        return path if path.is_file() else None

    def usage_bytes(self) -> int:
        now = time.monotonic()
        if self._usage is None or now - self._usage[0] > self._usage_ttl:
            total = 0
            for dirpath, _, filenames in os.walk(self.root):
                for name in filenames:
                    with contextlib.suppress(OSError):   # deleted meanwhile
                        total += os.stat(os.path.join(dirpath, name)).st_size
            self._usage = (now, total)
        return self._usage[1]

    # ------------------------------------------------------------------- events

    def append_event(self, prefix: str, event: dict, *, durable: bool = True) -> dict:
        path = self.path(prefix + EVENTS)
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            stored = {"seq": _last_seq(fd) + 1, "time": now_iso(), **event}
            line = (dumps(stored, indent=None) + "\n").encode()
            if os.write(fd, line) != len(line):
                raise StoreFull(errno.ENOSPC, "short write to the event log", str(path))
            if durable:
                os.fsync(fd)
            else:
                self._unflushed.add(path)
        except OSError as exc:
            raise _translated(exc, prefix + EVENTS) from exc
        finally:
            os.close(fd)  # releases the lock
        return stored

    def read_events(self, prefix: str, after: int = 0, cursor: Any = None) -> tuple[list[dict], Any]:
        path = self.path(prefix + EVENTS)
        offset = int(cursor or 0)
        try:
            with path.open("rb") as handle:
                handle.seek(offset)
                data = handle.read()
        except FileNotFoundError:
            return [], offset
        end = data.rfind(b"\n") + 1
        events = []
        for raw in data[:end].splitlines():
            try:
                event = json.loads(raw)
            except json.JSONDecodeError:
                continue
            if event.get("seq", 0) > after:
                events.append(event)
        return events, offset + end

    # -------------------------------------------------------------------- locks

    @contextmanager
    def _locked(self, key: str):
        path = self.path(key)
        lock = path.parent / f".{path.name}.lock"
        lock.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX)
            yield
        finally:
            os.close(fd)


def _last_seq(fd: int) -> int:
    """The ``seq`` of the last complete line of an event log opened at ``fd`` (0 when empty)."""
    end = os.lseek(fd, 0, os.SEEK_END)
    chunk = 4096
    while True:
        start = max(0, end - chunk)
        data = os.pread(fd, end - start, start)
        lines = data.rstrip(b"\n").split(b"\n")
        candidates = lines if start == 0 else lines[1:]
        for raw in reversed(candidates):
            try:
                return int(json.loads(raw)["seq"])
            except (ValueError, KeyError, TypeError):
                continue  # a torn line (killed writer): look further back
        if start == 0:
            return 0
        chunk *= 4


def _translated(exc: OSError, key: str) -> OSError:
    if isinstance(exc, StoreFull):
        return exc
    if exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG):
        return StoreFull(exc.errno, f"the artifact store is full ({os.strerror(exc.errno)}) writing {key}")
    return exc

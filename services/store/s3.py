"""The S3 store: ``NDRF_STORE=s3://bucket/prefix`` on any S3-compatible endpoint, so that workers
on several machines share no disk. Client: obstore (Rust ``object_store``: one dependency,
SigV4, retries, conditional puts, streaming; chosen by ``bench/investigations/store_clients.py``).

What the folder store does with rename, ``flock`` and ``O_APPEND``, here:

* ``put``: one PutObject (a multipart upload above 5 MiB, which S3 also publishes only when it
  completes): a reader sees the old object or the new one;
* ``put_if``: PutObject with ``If-None-Match: *`` (create) or ``If-Match: <etag>`` (update); the
  server decides atomically, so of two writers on two machines exactly one wins. The version is
  the object's ETag. A 409 ``ConditionalRequestConflict`` (S3's answer to a concurrent
  conditional write) counts as a lost race: nothing of ours was written;
* the event log of ``<prefix>`` is one object per event, ``<prefix>events/000000000042.json``,
  created with ``If-None-Match: *``: an appender that loses number 42 to another re-lists after
  the key it knew and tries the next free number, so numbers are consecutive and a later event is
  created only once every earlier one is readable. Readers list after the key of the last event
  they have (ListObjectsV2 ``start-after``), which is the ``Last-Event-ID`` replay.

The server must implement conditional writes atomically (AWS S3, SeaweedFS >= 4.18 and others do;
some emulators check and write in two steps). Credentials and region come from the usual AWS
environment variables (``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_REGION``...).
"""

from __future__ import annotations

import io
import json
import logging
import threading
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from datetime import UTC, datetime, timedelta
from typing import Any, BinaryIO
from urllib.parse import urlparse

import obstore
from obstore.exceptions import AlreadyExistsError, NotFoundError, PreconditionError
from obstore.store import S3Store as _Client

from services.store.base import ArtifactStore, StoreFull
from services.store.files import dumps

log = logging.getLogger(__name__)

EVENTS = "events/"
SEQ_DIGITS = 12
CONTENT_TYPES = {"png": "image/png", "json": "application/json", "npy": "application/octet-stream",
                 "pt": "application/octet-stream"}
_MISSING = (FileNotFoundError, NotFoundError)


def parse_url(url: str) -> tuple[str, str]:
    """``s3://bucket/some/prefix`` -> ``("bucket", "some/prefix")``."""
    parsed = urlparse(url)
    if parsed.scheme != "s3" or not parsed.netloc:
        raise ValueError(f"an S3 store is named s3://bucket[/prefix], not {url!r}")
    return parsed.netloc, parsed.path.strip("/")


def event_key(prefix: str, seq: int) -> str:
    return f"{prefix}{EVENTS}{seq:0{SEQ_DIGITS}d}.json"


def _now_iso() -> str:
    return datetime.now(UTC).isoformat(timespec="milliseconds")


def _conflict(exc: Exception) -> bool:
    """A 409 from a conditional write (S3: ``ConditionalRequestConflict``)."""
    text = str(exc)
    return "409 Conflict" in text or "<Code>ConditionalRequestConflict</Code>" in text


def _full(exc: Exception) -> bool:
    if isinstance(exc, (AlreadyExistsError, PreconditionError, *_MISSING)):
        return False
    text = str(exc)
    return any(s in text for s in ("507 Insufficient Storage", "<Code>QuotaExceeded</Code>",
                                   "<Code>XMinioStorageFull</Code>", "<Code>EntityTooLarge</Code>"))


class S3Store(ArtifactStore):
    """Objects of one bucket under one prefix.

    ``endpoint``          S3-compatible endpoint URL (None: AWS S3 of the region)
    ``presign_bytes``     objects at least this large are served by redirect to a pre-signed URL
                          (0: never; the API then streams them through itself)
    ``presign_seconds``   lifetime of a pre-signed URL
    ``public_endpoint``   the endpoint as clients outside see it, for pre-signed URLs
    ``usage_ttl``         seconds a computed :meth:`usage_bytes` is reused (it lists the bucket)
    """

    def __init__(self, url: str, *, endpoint: str | None = None, presign_bytes: int = 0,
                 presign_seconds: int = 300, public_endpoint: str | None = None, usage_ttl: float = 300.0,
                 **client_config: Any):
        self.url = url
        self.bucket, self.prefix = parse_url(url)
        self.endpoint = endpoint or None
        self.client = self._client(self.endpoint, client_config)
        signer = public_endpoint or None
        self.signer = self._client(signer, client_config) if signer and signer != self.endpoint else self.client
        self.presign_bytes, self.presign_seconds = presign_bytes, presign_seconds
        self._usage: tuple[float, int] | None = None
        self._usage_ttl = usage_ttl
        self._last_seq: dict[str, int] = {}       # per event log: the last number known to exist
        self._seq_lock = threading.Lock()
        self._pool: ThreadPoolExecutor | None = None

    def _client(self, endpoint: str | None, config: dict[str, Any]) -> _Client:
        options: Any = {"allow_http": True} if endpoint and endpoint.startswith("http://") else {}
        rest = dict(config)
        options |= rest.pop("client_options", {})
        given = {"prefix": self.prefix, "endpoint": endpoint, "client_options": options}
        return _Client(self.bucket, **{k: v for k, v in given.items() if v}, **rest)

    def __repr__(self) -> str:
        return f"S3Store({self.url!r}, endpoint={self.endpoint!r})"

    @staticmethod
    def check(key: str) -> str:
        parts = key.split("/")
        if not key or key.startswith("/") or ".." in parts or "." in parts or "\\" in key or "" in parts[:-1]:
            raise ValueError(f"store key {key!r} must be a relative path without '..' or empty parts")
        return key

    # ------------------------------------------------------------------ objects

    def get(self, key: str) -> bytes | None:
        try:
            return bytes(obstore.get(self.client, self.check(key)).bytes())
        except _MISSING:
            return None

    def put(self, key: str, data: bytes, *, durable: bool = True) -> None:
        self._put(key, data, None)   # a PUT that succeeded is durable

    def put_file(self, key: str, handle: BinaryIO, size: int) -> None:
        self._put(key, _chunks(handle, size), None)   # a multipart upload above 5 MiB, chunk by chunk

    def _put(self, key: str, data: Any, mode: Any) -> str | None:
        ext = key.rsplit(".", 1)[-1]
        attributes: Any = {"Content-Type": CONTENT_TYPES[ext]} if ext in CONTENT_TYPES else None
        try:
            result = obstore.put(self.client, self.check(key), data, mode=mode, attributes=attributes)
        except Exception as exc:
            if _full(exc):
                raise StoreFull(28, f"the artifact store is full writing {key}: {exc}") from exc
            raise
        return result["e_tag"]

    def get_versioned(self, key: str) -> tuple[bytes, str] | None:
        try:
            got = obstore.get(self.client, self.check(key))
        except _MISSING:
            return None
        etag = got.meta["e_tag"]
        if etag is None:
            raise RuntimeError(f"the S3 endpoint returned no ETag for {key}: conditional writes need one")
        return bytes(got.bytes()), etag

    def put_if(self, key: str, data: bytes, version: str | None) -> str | None:
        mode: Any = "create" if version is None else {"e_tag": version}
        try:
            return self._put(key, data, mode) or ""
        except (AlreadyExistsError, PreconditionError, *_MISSING):
            return None
        except Exception as exc:
            if _conflict(exc):
                return None
            raise

    def exists(self, key: str) -> bool:
        return self.size(key) is not None

    def size(self, key: str) -> int | None:
        try:
            return int(obstore.head(self.client, self.check(key))["size"])
        except _MISSING:
            return None

    def _list(self, prefix: str, offset: str | None = None) -> Iterator[Any]:
        """Object metadata under the string ``prefix`` (any key that starts with it), in key order."""
        folder = prefix.rpartition("/")[0]
        for chunk in obstore.list(self.client, prefix=folder or None, offset=offset):
            for meta in chunk:
                if meta["path"].startswith(prefix):
                    yield meta

    def keys(self, prefix: str, *, delimiter: bool = False) -> Iterator[str]:
        if delimiter:
            folder = prefix.rpartition("/")[0]
            listing = obstore.list_with_delimiter(self.client, folder or None)
            names = [p + "/" for p in listing["common_prefixes"]] + [o["path"] for o in listing["objects"]]
            yield from sorted(n for n in names if n.startswith(prefix) and not _hidden(n.rstrip("/")))
            return
        yield from (meta["path"] for meta in self._list(prefix) if not _hidden(meta["path"]))

    def prefix_bytes(self, prefix: str) -> int:
        return sum(int(meta["size"]) for meta in self._list(prefix))

    def delete_prefix(self, prefix: str) -> int:
        """Objects under ``prefix`` (a folder when it ends in ``/``; else the object ``prefix`` and
        the folder ``prefix/``), deleted with batched DeleteObjects."""
        if prefix:
            self.check(prefix.rstrip("/"))
        scope = prefix if prefix.endswith("/") or not prefix else prefix + "/"
        metas: list[Any] = list(self._list(scope))
        if prefix and not prefix.endswith("/"):
            single = self.size(prefix)
            if single is not None:
                metas.append({"path": prefix, "size": single})
        for start in range(0, len(metas), 1000):
            obstore.delete(self.client, [m["path"] for m in metas[start:start + 1000]])
        with self._seq_lock:
            for log_prefix in [p for p in self._last_seq if p.startswith(scope)]:
                del self._last_seq[log_prefix]
        self._usage = None
        return sum(int(m["size"]) for m in metas)

    def open(self, key: str) -> BinaryIO | None:
        try:
            got = obstore.get(self.client, self.check(key))
        except _MISSING:
            return None
        return io.BufferedReader(_Stream(got.stream(min_chunk_size=1 << 16)), buffer_size=1 << 16)

    def get_range(self, key: str, start: int, length: int) -> bytes | None:
        size = self.size(key)
        if size is None:
            return None
        end = min(size, start + length)
        if end <= start:
            return b""
        try:
            return bytes(obstore.get_range(self.client, self.check(key), start=start, end=end))
        except _MISSING:
            return None

    def redirect_url(self, key: str) -> str | None:
        """A pre-signed GET URL when the object is at least ``presign_bytes`` large (else None)."""
        if self.presign_bytes <= 0:
            return None
        size = self.size(key)
        if size is None or size < self.presign_bytes:
            return None
        return obstore.sign(self.signer, "GET", self.check(key), timedelta(seconds=self.presign_seconds))

    def usage_bytes(self) -> int:
        now = time.monotonic()
        if self._usage is None or now - self._usage[0] > self._usage_ttl:
            total = sum(int(meta["size"]) for chunk in obstore.list(self.client) for meta in chunk)
            self._usage = (now, total)
        return self._usage[1]

    # ------------------------------------------------------------------- events

    def append_event(self, prefix: str, event: dict, *, durable: bool = True) -> dict:
        with self._seq_lock:
            known = self._last_seq.get(prefix)
        seq = (self._last_listed_seq(prefix, 0) if known is None else known) + 1
        while True:
            stored = {"seq": seq, "time": _now_iso(), **event}
            if self.put_if(event_key(prefix, seq), (dumps(stored, indent=None) + "\n").encode(), None) is not None:
                with self._seq_lock:
                    self._last_seq[prefix] = max(seq, self._last_seq.get(prefix, 0))
                return stored
            seq = self._last_listed_seq(prefix, seq) + 1   # taken: another appender got there first

    def _last_seq_of(self, key: str) -> int:
        return int(key.rsplit("/", 1)[-1].split(".", 1)[0])

    def _last_listed_seq(self, prefix: str, at_least: int) -> int:
        """The largest event number of the log (listing after event ``at_least``, which exists)."""
        after = event_key(prefix, at_least) if at_least else None
        last = at_least
        for meta in self._list(prefix + EVENTS, offset=after):
            last = max(last, self._last_seq_of(meta["path"]))
        return last

    def read_events(self, prefix: str, after: int = 0, cursor: Any = None) -> tuple[list[dict], Any]:
        start = max(int(after or 0), int(cursor or 0))
        keys = [m["path"] for m in self._list(prefix + EVENTS, offset=event_key(prefix, start) if start else None)]
        if not keys:
            return [], start
        datas = self._fetch(keys)
        events = []
        for data in datas:
            if data is None:      # deleted meanwhile (the job was deleted)
                break
            events.append(json.loads(data))
        last = events[-1]["seq"] if events else start
        return [e for e in events if e.get("seq", 0) > after], last

    def _fetch(self, keys: list[str]) -> list[bytes | None]:
        """GET several small objects, in parallel when there are many (a replay of a long job)."""
        if len(keys) <= 2:
            return [self.get(k) for k in keys]
        if self._pool is None:
            self._pool = ThreadPoolExecutor(max_workers=8, thread_name_prefix="s3-events")
        return list(self._pool.map(self.get, keys))

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=False)
            self._pool = None


def _chunks(handle: BinaryIO, size: int) -> Iterator[bytes]:
    """The first ``size`` bytes of ``handle``, 1 MiB at a time (an ``OSError`` if it is shorter)."""
    left = size
    while left:
        chunk = handle.read(min(left, 1 << 20))
        if not chunk:
            raise OSError(f"the file ended {left} bytes short of {size}")
        left -= len(chunk)
        yield chunk


def _hidden(key: str) -> bool:
    """Keys with a part starting with ``.`` (``.idempotency/``, ``.healthz``) are not listed,
    as the folder store does not list hidden files."""
    return any(part.startswith(".") for part in key.split("/"))


class _Stream(io.RawIOBase):
    """A raw, read-only stream over obstore's chunk iterator (for ``io.BufferedReader``)."""

    def __init__(self, chunks: Iterator[bytes]):
        self._chunks = iter(chunks)
        self._pending = memoryview(b"")

    def readable(self) -> bool:
        return True

    def readinto(self, buffer) -> int:
        while not self._pending:
            try:
                self._pending = memoryview(bytes(next(self._chunks)))
            except StopIteration:
                return 0
        n = min(len(buffer), len(self._pending))
        buffer[:n] = self._pending[:n]
        self._pending = self._pending[n:]
        return n

"""Atomic file writes: a reader (or a resumed job) never sees a torn file, even after SIGKILL.

Each write goes to a temporary file in the same folder, is flushed to disk, and is renamed over
the destination (``os.replace`` is atomic on POSIX within one file system).
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, BinaryIO

import numpy as np


def atomic_write_bytes(path: str | Path, data: bytes, *, sync: bool = True) -> Path:
    path = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    except FileNotFoundError:  # a new folder, made here once rather than checked on every write
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as handle:
            handle.write(data)
            handle.flush()
            if sync:
                os.fsync(handle.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


#: Bytes copied at a time by :func:`atomic_copy` (a file is never read whole into memory).
CHUNK_BYTES = 1 << 20


def atomic_copy(path: str | Path, handle: BinaryIO, size: int) -> Path:
    """:func:`atomic_write_bytes` of the first ``size`` bytes of ``handle``, in chunks of
    :data:`CHUNK_BYTES`: a file shorter than ``size`` is an ``OSError`` (nothing written)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as out:
            left = size
            while left:
                chunk = handle.read(min(left, CHUNK_BYTES))
                if not chunk:
                    raise OSError(f"{path.name}: the file ended {left} bytes short of {size}")
                out.write(chunk)
                left -= len(chunk)
            out.flush()
            os.fsync(out.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def _default(value: Any):
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot serialise {type(value).__name__} to JSON")


def dumps(value: Any, indent: int | None = 2) -> str:
    """JSON with numpy support; non-finite floats are written as null (JSON has no NaN)."""
    separators = None if indent else (",", ":")
    return json.dumps(_finite(value), default=_default, indent=indent, separators=separators, allow_nan=False)


def _finite(value: Any):
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    if isinstance(value, np.ndarray):
        return _finite(value.tolist())
    return value


def atomic_write_json(path: str | Path, value: Any) -> Path:
    return atomic_write_bytes(path, (dumps(value) + "\n").encode())


def atomic_write_npy(path: str | Path, array: np.ndarray) -> Path:
    from services.store.images import npy_bytes

    return atomic_write_bytes(path, npy_bytes(array))


def read_json(path: str | Path) -> Any:
    return json.loads(Path(path).read_text())

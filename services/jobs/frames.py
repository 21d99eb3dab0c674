"""The wire format between a sandboxed child process and its parent: length-prefixed frames.

    frame  = u64 big-endian header length | header (UTF-8 JSON) | blob_1 | ... | blob_n
    header = {"kind": str, "meta": {...}, "blobs": [[name, length], ...]}

Arrays travel as ``.npy`` bytes read back with ``allow_pickle=False``, checkpoints as opaque
bytes: nothing the parent reads from a child can run code in the parent, even if a hostile scene
took the child over. The parent bounds every length it reads.
"""

from __future__ import annotations

import io
import json
import struct
from typing import BinaryIO

import numpy as np

MAX_HEADER_BYTES = 16 << 20
MAX_BLOB_BYTES = 4 << 30


class FrameError(ValueError):
    """A malformed frame (a crashed or hostile child)."""


def write_frame(stream: BinaryIO, kind: str, meta: dict | None = None, blobs: dict[str, bytes] | None = None) -> None:
    blobs = blobs or {}
    header = json.dumps({"kind": kind, "meta": meta or {}, "blobs": [[k, len(v)] for k, v in blobs.items()]},
                        allow_nan=False).encode()
    stream.write(struct.pack(">Q", len(header)) + header)
    for data in blobs.values():
        stream.write(data)
    stream.flush()


def read_frame(stream: BinaryIO) -> tuple[str, dict, dict[str, bytes]] | None:
    """The next frame, or None at a clean end of stream."""
    first = stream.read(1)
    if not first:
        return None  # a clean end of stream, between frames
    head = first + _read_exactly(stream, 7)
    (length,) = struct.unpack(">Q", head)
    if length > MAX_HEADER_BYTES:
        raise FrameError(f"frame header of {length} bytes exceeds {MAX_HEADER_BYTES}")
    try:
        header = json.loads(_read_exactly(stream, length))
        kind, meta, table = str(header["kind"]), dict(header["meta"]), list(header["blobs"])
    except (ValueError, KeyError, TypeError) as exc:
        raise FrameError(f"malformed frame header: {exc}") from None
    blobs = {}
    for name, size in table:
        if not isinstance(size, int) or not 0 <= size <= MAX_BLOB_BYTES:
            raise FrameError(f"blob {name!r} of {size} bytes is out of range")
        blobs[str(name)] = _read_exactly(stream, size)
    return kind, meta, blobs


def _read_exactly(stream: BinaryIO, n: int) -> bytes:
    chunks, left = [], n
    while left:
        chunk = stream.read(left)
        if not chunk:
            raise FrameError(f"stream ended {left} bytes before the end of a frame")
        chunks.append(chunk)
        left -= len(chunk)
    return b"".join(chunks)


def array_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(array), allow_pickle=False)
    return buffer.getvalue()


def array_from(data: bytes, *, dtype=np.float32, ndim: int | None = None) -> np.ndarray:
    """Read an array sent by a child: numeric dtypes only, no pickles."""
    try:
        array = np.load(io.BytesIO(data), allow_pickle=False)
    except ValueError as exc:
        raise FrameError(f"not an array: {exc}") from None
    if array.dtype.kind not in "fiu" or (ndim is not None and array.ndim != ndim):
        raise FrameError(f"unexpected array {array.dtype} with shape {array.shape}")
    return array.astype(dtype, copy=False)


def start_frame(start: dict) -> tuple[dict, dict[str, bytes]]:
    """The ``start`` frame of a child: an uploaded scene's files (base64 in the job's spec, up to
    the upload limit, more than a header may hold) travel as blobs; :func:`started` puts them back."""
    spec = start.get("spec")
    files = spec.get("scene", {}).get("files") if isinstance(spec, dict) else None
    if not files or not isinstance(spec, dict):
        return start, {}
    names = sorted(files)
    meta = dict(start, spec=dict(spec, scene=dict(spec["scene"], files={})), scene_files=names)
    return meta, {f"file-{i}": files[name].encode("ascii") for i, name in enumerate(names)}


def started(meta: dict, blobs: dict[str, bytes]) -> dict:
    """The ``start`` dict :func:`start_frame` split: the spec's scene files restored."""
    names = meta.get("scene_files")
    if not names:
        return meta
    files = {str(name): blobs[f"file-{i}"].decode("ascii") for i, name in enumerate(names)}
    spec = dict(meta["spec"], scene=dict(meta["spec"]["scene"], files=files))
    return {k: v for k, v in dict(meta, spec=spec).items() if k != "scene_files"}


def outcome_frame(outcome: dict) -> tuple[dict, dict[str, bytes]]:
    """The ``outcome`` frame of a child: a shape job's recovered meshes (base64 PLY, about 50 bytes
    a vertex of a closed mesh, past the header's limit from about 335,000 vertices) travel as blobs;
    :func:`outcome_of` puts them back."""
    meshes = outcome.get("meshes")
    if not meshes:
        return outcome, {}
    names = sorted(shape for shape, mesh in meshes.items() if "ply" in mesh)
    kept = {shape: ({k: v for k, v in mesh.items() if k != "ply"} if shape in names else mesh)
            for shape, mesh in meshes.items()}
    meta = dict(outcome, meshes=kept, mesh_blobs=names)
    return meta, {f"mesh-{i}": meshes[shape]["ply"].encode("ascii") for i, shape in enumerate(names)}


def outcome_of(meta: dict, blobs: dict[str, bytes]) -> dict:
    """The outcome dict :func:`outcome_frame` split: the meshes' PLY restored."""
    names = meta.get("mesh_blobs")
    if not names:
        return meta
    try:
        meshes = dict(meta["meshes"])
        for i, shape in enumerate(names):
            meshes[str(shape)] = dict(meshes[shape], ply=blobs[f"mesh-{i}"].decode("ascii"))
    except (KeyError, TypeError, UnicodeDecodeError) as exc:
        raise FrameError(f"malformed outcome meshes: {exc}") from None
    return {k: v for k, v in dict(meta, meshes=meshes).items() if k != "mesh_blobs"}

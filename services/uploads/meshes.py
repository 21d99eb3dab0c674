"""Check an uploaded mesh (PLY, Wavefront OBJ, Mitsuba ``serialized``) before Mitsuba reads it.

Why: Mitsuba 3.9's mesh readers trust their headers. The PLY and ``serialized`` readers store the
declared counts in 32-bit integers and size their buffers as ``uint32(count) * 3``: a PLY header
``element vertex 4294967297`` allocates one vertex and then writes every float of the file past it
(heap overflow). They never check face indices either, and ``recompute_vertex_normals`` writes
``normals[index]`` for every corner: an index past the vertex count is an out-of-bounds write.
``serialized`` meshes are zlib streams whose declared counts decide how much is inflated.

The rules, each refused with ``InvalidJob("scene.files[<path>]", ...)`` naming the limit:

* every declared count is a plain decimal below 2^31, and at most ``max_mesh_vertices`` vertices
  and ``max_mesh_faces`` faces (triangles) per mesh; neither cap may exceed ``(2^32 - 1) / 3``,
  where Mitsuba's ``uint32(count) * 3`` would wrap;
* binary PLY: the body after the header must hold every declared element (at least the count
  byte(s) of each list entry; a file too short for its counts is refused), and, since Mitsuba
  reads every list as a triangle (count + 3 entries) and refuses trailing bytes, exactly
  ``sum(count x stride)`` bytes; every list has 3 entries and every face index is within the
  vertex count (checked with numpy on the raw bytes, nothing is copied);
* ASCII PLY: the number of whitespace-separated values after the header equals what the header
  declares (the same triangle rule), and face indices are integers within the vertex count;
* unknown PLY property types, formats and header lines are refused (Mitsuba refuses them too);
* OBJ has no declared counts: the vertex lines and the triangles of the face lines (a polygon of
  n corners becomes n - 2 triangles) are counted and capped; Mitsuba itself refuses out-of-range
  OBJ indices, so they are not re-checked here;
* ``serialized``: the header, the end-of-file table of shape offsets and each shape's zlib stream
  are parsed; each stream is inflated incrementally (``zlib.decompressobj`` with ``max_length``),
  never beyond what its declared counts need, and those sizes are capped in total by
  ``max_mesh_decompressed_bytes`` before inflating; a stream shorter than its counts is refused;
  face indices are checked against the vertex count chunk by chunk.

The result is a :class:`MeshSummary` (vertices, faces, bytes) that the caller sums over every
reference to the file, so that one mesh referenced 50,000 times costs 50,000 times.
"""

from __future__ import annotations

import itertools
import logging
import re
import struct
import zlib
from collections.abc import Iterator

import numpy as np

from services.uploads.mesh_base import (
    CHUNK,
    MAX_COUNT,
    MAX_MESH_COUNT,
    MESH_TYPES,
    MeshLimits,
    MeshSummary,
    check_count,
    refuse,
)
from services.uploads.mesh_ply import check_ply

log = logging.getLogger(__name__)

__all__ = ["MAX_COUNT", "MAX_MESH_COUNT", "MESH_TYPES", "MeshLimits", "MeshSummary", "check_mesh", "mesh_kind"]

_SERIALIZED_NAME_BYTES = 4096  # shape name inside a serialized stream (NUL-terminated)


def mesh_kind(path: str, shape_type: str | None = None) -> str | None:
    """The format to check: the shape's ``type`` if it is a mesh type, else the extension."""
    if shape_type in MESH_TYPES:
        return shape_type
    extension = path.rsplit(".", 1)[-1].lower() if "." in path.rsplit("/", 1)[-1] else ""
    return extension if extension in MESH_TYPES else None


def check_mesh(path: str, data: bytes, limits: MeshLimits = MeshLimits(),
               kind: str | None = None) -> MeshSummary:
    """Check one uploaded mesh file; ``kind`` is the referencing shape's type (``ply``, ``obj``,
    ``serialized``), else the extension decides. Raises InvalidJob on ``scene.files[path]``."""
    fmt = mesh_kind(path, kind)
    if fmt is None:
        raise refuse(path, f"is not a mesh Mitsuba can read: expected one of {', '.join(MESH_TYPES)} "
                            "(by the shape's type or the file extension)")
    checker = {"ply": check_ply, "obj": _check_obj, "serialized": _check_serialized}[fmt]
    summary = checker(path, memoryview(data).toreadonly(), limits)
    log.debug("mesh %s: %s, %d vertices, %d faces", path, fmt, summary.vertices, summary.faces)
    return summary


# ------------------------------------------------------------------------------------------ OBJ

_OBJ_VERTEX = re.compile(rb"^[ \t\r]*v[ \t]", re.MULTILINE)
_OBJ_FACE = re.compile(rb"^[ \t\r]*f[ \t]([^\n]*)", re.MULTILINE)


def _check_obj(path: str, data: memoryview, limits) -> MeshSummary:
    """Count ``v`` lines and the triangles of ``f`` lines (n corners -> n - 2), as Mitsuba's
    reader recognizes them (a line's first word after spaces, tabs and carriage returns)."""
    text = bytes(data)
    vertices = sum(1 for _ in _OBJ_VERTEX.finditer(text))
    check_count(path, "vertices ('v' lines)", vertices, limits.max_mesh_vertices, "max_mesh_vertices", "has")
    faces = 0
    cap = min(limits.max_mesh_faces, MAX_MESH_COUNT)
    for match in _OBJ_FACE.finditer(text):
        faces += max(len(match[1].split()) - 2, 0)
        if faces > cap:
            raise refuse(path, f"has more than {cap} triangles (faces with n corners count n - 2); at most "
                                f"{cap} are allowed per mesh (max_mesh_faces)")
    return MeshSummary("obj", vertices, faces, len(data))


# ----------------------------------------------------------------------------------- serialized

_SERIALIZED_MAGIC = 0x041C
_HAS_NORMALS, _HAS_TEXCOORDS, _HAS_COLORS, _DOUBLE = 0x0001, 0x0002, 0x0008, 0x2000


class _Inflater:
    """Inflate one zlib stream a bounded piece at a time: nothing beyond what is asked for is
    ever decompressed (``decompressobj.decompress(..., max_length)``)."""

    def __init__(self, source: memoryview):
        self._source = source
        self._taken = 0
        self._zlib = zlib.decompressobj()
        self.produced = 0

    def _pull(self, want: int) -> bytes:
        while not self._zlib.eof:
            data: bytes | memoryview = self._zlib.unconsumed_tail
            if not data:
                if self._taken >= len(self._source):
                    return b""
                data = self._source[self._taken:self._taken + CHUNK]
                self._taken += len(data)
            out = self._zlib.decompress(data, want)
            if out:
                self.produced += len(out)
                return out
        return b""

    def chunks(self, size: int, chunk: int = CHUNK) -> Iterator[bytes]:
        """Exactly ``size`` bytes in pieces of ``chunk`` (the last may be shorter); raise EOFError
        when the stream ends first."""
        while size > 0:
            piece = b""
            want = min(size, chunk)
            while len(piece) < want:
                out = self._pull(want - len(piece))
                if not out:
                    raise EOFError
                piece += out
            size -= len(piece)
            yield piece

    def read(self, size: int) -> bytes:
        return b"".join(self.chunks(size))


def _check_serialized(path: str, data: memoryview, limits) -> MeshSummary:
    if len(data) < 10:
        raise refuse(path, "is too short to be a Mitsuba serialized mesh")
    magic, version = struct.unpack_from("<HH", data, 0)
    if magic != _SERIALIZED_MAGIC or version not in (3, 4):
        raise refuse(path, "is not a Mitsuba serialized mesh (expected identifier 0x041C, version 3 or 4)")
    offsets, table = _serialized_offsets(path, data, version)
    used = 0
    shapes = []
    for index, offset in enumerate(offsets):
        end = offsets[index + 1] if index + 1 < len(offsets) else table
        if struct.unpack_from("<HH", data, offset) != (magic, version):
            raise refuse(path, f"shape {index} at offset {offset} does not start with the file's header")
        shape, inflated = _serialized_shape(path, index, data[offset + 4:end], version, limits, used)
        used += inflated
        shapes.append(shape)
    return MeshSummary("serialized", sum(s.vertices for s in shapes), sum(s.faces for s in shapes), len(data),
                       tuple(shapes))


def _serialized_offsets(path: str, data: memoryview, version: int) -> tuple[list[int], int]:
    """The end-of-file table: one offset per shape (uint64, uint32 in version 3) then the shape
    count (uint32). Offsets start at 0 and increase; returns (offsets, start of the table)."""
    (count,) = struct.unpack_from("<I", data, len(data) - 4)
    width = 8 if version == 4 else 4
    table = len(data) - 4 - count * width
    if count < 1 or count > MAX_COUNT or table < 4:
        raise refuse(path, f"has an invalid end-of-file shape table: {count} shapes do not fit in "
                            f"{len(data)} bytes")
    offsets = list(struct.unpack_from(f"<{count}{'Q' if width == 8 else 'I'}", data, table))
    if offsets[0] != 0 or any(b - a < 6 for a, b in itertools.pairwise(offsets)) or table - offsets[-1] < 6:
        raise refuse(path, "has an invalid end-of-file shape table: offsets must start at 0, increase, "
                            "and stay before the table")
    return offsets, table


def _serialized_shape(path: str, index: int, stream: memoryview, version: int, limits,
                      used: int) -> tuple[MeshSummary, int]:
    """Check one shape's zlib stream (``used`` bytes were inflated for the shapes before it);
    returns its summary and the bytes inflated."""
    where = f"shape {index}"
    inflater = _Inflater(stream)
    try:
        (flags,) = struct.unpack("<I", inflater.read(4))
        if version == 4:
            for byte in inflater.chunks(_SERIALIZED_NAME_BYTES + 1, 1):
                if byte == b"\0":
                    break
            else:
                raise refuse(path, f"{where}: the shape name is longer than {_SERIALIZED_NAME_BYTES} bytes")
        vertices, faces = struct.unpack("<QQ", inflater.read(16))
    except EOFError:
        raise refuse(path, f"{where}: the compressed stream ends inside the mesh header") from None
    except zlib.error as exc:
        raise refuse(path, f"{where}: invalid compressed data ({exc})") from None
    check_count(path, f"vertices in {where}", vertices, limits.max_mesh_vertices, "max_mesh_vertices")
    check_count(path, f"faces in {where}", faces, limits.max_mesh_faces, "max_mesh_faces")
    real = 8 if flags & _DOUBLE else 4
    per_vertex = 3 + 3 * bool(flags & _HAS_NORMALS) + 2 * bool(flags & _HAS_TEXCOORDS) + 3 * bool(flags & _HAS_COLORS)
    arrays = vertices * per_vertex * real
    total = inflater.produced + arrays + faces * 12
    if used + total > limits.max_mesh_decompressed_bytes:
        before = f" ({used + total} with the shapes before it)" if used else ""
        raise refuse(path, f"{where}: {vertices} vertices and {faces} faces decompress to {total} bytes{before}; "
                            f"at most {limits.max_mesh_decompressed_bytes} bytes per file are allowed "
                            "(max_mesh_decompressed_bytes)")
    try:
        for _ in inflater.chunks(arrays):
            pass
        for piece in inflater.chunks(faces * 12, CHUNK - CHUNK % 12):
            indices = np.frombuffer(piece, dtype="<u4")
            if indices.max() >= vertices:
                raise refuse(path, f"{where}: face index {int(indices.max())} is out of range (the shape has "
                                    f"{vertices} vertices)")
    except EOFError:
        raise refuse(path, f"{where}: declares {vertices} vertices and {faces} faces ({total} bytes), but its "
                            f"compressed stream ends after {inflater.produced} bytes") from None
    except zlib.error as exc:
        raise refuse(path, f"{where}: invalid compressed data ({exc})") from None
    return MeshSummary("serialized", vertices, faces, len(stream) + 4), inflater.produced

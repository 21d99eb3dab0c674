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
from dataclasses import dataclass

import numpy as np

from schemas.errors import InvalidJob

log = logging.getLogger(__name__)

MAX_COUNT = 2**31 - 1  # every declared count must be below 2^31
MAX_MESH_COUNT = (2**32 - 1) // 3  # Mitsuba sizes buffers as uint32(count) * 3
MESH_TYPES = ("ply", "obj", "serialized")  # Mitsuba shape types that read a mesh file

_PLY_HEADER_BYTES = 64 << 10  # a real PLY header is a few hundred bytes
_SERIALIZED_NAME_BYTES = 4096  # shape name inside a serialized stream (NUL-terminated)
_CHUNK = 1 << 20  # bytes inflated or parsed at a time


@dataclass(frozen=True)
class MeshLimits:
    """The caps this module applies; :class:`services.uploads.scene.UploadLimits` has the same
    fields and can be passed instead."""

    max_mesh_vertices: int = 10_000_000
    max_mesh_faces: int = 20_000_000
    max_mesh_decompressed_bytes: int = 256 << 20


@dataclass(frozen=True)
class MeshSummary:
    """What loading the file costs: ``vertices`` and ``faces`` (triangles) Mitsuba will build,
    ``bytes`` of the file it reads. For ``serialized``, ``shapes`` has one summary per sub-shape
    (``bytes`` = its compressed stream), since a shape loads one of them (``shape_index``)."""

    format: str
    vertices: int
    faces: int
    bytes: int
    shapes: tuple[MeshSummary, ...] = ()

    def shape(self, index: int) -> MeshSummary:
        """The summary of what ``shape_index=index`` loads (the whole file for PLY/OBJ)."""
        if not self.shapes:
            return self
        return self.shapes[index]


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
        raise _refuse(path, f"is not a mesh Mitsuba can read: expected one of {', '.join(MESH_TYPES)} "
                            "(by the shape's type or the file extension)")
    checker = {"ply": _check_ply, "obj": _check_obj, "serialized": _check_serialized}[fmt]
    summary = checker(path, memoryview(data).toreadonly(), limits)
    log.debug("mesh %s: %s, %d vertices, %d faces", path, fmt, summary.vertices, summary.faces)
    return summary


def _refuse(path: str, message: str) -> InvalidJob:
    return InvalidJob(f"scene.files[{path}]", message)


def _check_count(path: str, what: str, count: int, cap: int, cap_name: str, verb: str = "declares") -> None:
    if count > MAX_COUNT:
        raise _refuse(path, f"{verb} {count} {what}; counts must be below 2^31")
    cap = min(cap, MAX_MESH_COUNT)
    if count > cap:
        raise _refuse(path, f"{verb} {count} {what}; at most {cap} are allowed per mesh ({cap_name})")


# ------------------------------------------------------------------------------------------ PLY

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "long": "i8", "ulong": "u8",
    "half": "f2", "float16": "f2", "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}
_FACE_LISTS = ("vertex_indices", "vertex_index")  # the face list Mitsuba reads
_WHITESPACE = np.zeros(256, dtype=bool)
_WHITESPACE[list(b" \t\n\r\v\f")] = True


@dataclass
class _PlyProperty:
    name: str
    type: str  # numpy type code
    count_type: str | None = None  # set for a list


@dataclass
class _PlyElement:
    name: str
    count: int
    properties: list[_PlyProperty]

    def tokens(self) -> int:
        """Values per row as Mitsuba reads them (a list is its count and 3 entries)."""
        return sum(4 if p.count_type else 1 for p in self.properties)

    def min_tokens(self) -> int:
        return len(self.properties)

    def stride(self) -> int:
        return sum(int(p.count_type[1]) + 3 * int(p.type[1]) if p.count_type else int(p.type[1])
                   for p in self.properties)

    def min_stride(self) -> int:
        return sum(int((p.count_type or p.type)[1]) for p in self.properties)


def _check_ply(path: str, data: memoryview, limits) -> MeshSummary:
    fmt, elements, start = _ply_header(path, data)
    for element in elements:
        if element.name == "vertex":
            _check_count(path, "vertices", element.count, limits.max_mesh_vertices, "max_mesh_vertices")
        elif element.name == "face":
            _check_count(path, "faces", element.count, limits.max_mesh_faces, "max_mesh_faces")
        else:
            _check_count(path, f"'{element.name}' elements", element.count, MAX_COUNT, "2^31")
    vertices = sum(e.count for e in elements if e.name == "vertex")
    body = data[start:]
    if fmt == "ascii":
        _check_ply_ascii(path, body, elements, vertices)
    else:
        _check_ply_binary(path, body, elements, vertices, "<" if fmt == "binary_little_endian" else ">")
    faces = sum(e.count for e in elements if e.name == "face")
    return MeshSummary("ply", vertices, faces, len(data))


def _ply_header(path: str, data: memoryview) -> tuple[str, list[_PlyElement], int]:
    """(format, elements, offset of the body) from the header lines up to ``end_header``."""
    head = bytes(data[:_PLY_HEADER_BYTES])
    first = head.find(b"\n")
    if first < 0 or head[:first].strip() != b"ply":
        raise _refuse(path, "is not a PLY file: it must start with a 'ply' line")
    fmt = None
    elements: list[_PlyElement] = []
    pos = first + 1
    while True:
        end = head.find(b"\n", pos)
        if end < 0:
            raise _refuse(path, f"has no 'end_header' line in its first {_PLY_HEADER_BYTES} bytes")
        try:
            words = head[pos:end].decode("ascii").split()
        except UnicodeDecodeError:
            raise _refuse(path, "has a PLY header that is not ASCII text") from None
        line, pos = " ".join(words), end + 1
        if not words or words[0] == "comment":
            continue
        if words[0] == "end_header" and len(words) == 1:
            break
        if words[0] == "format":
            if fmt or len(words) != 3 or words[2] != "1.0" or \
                    words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise _refuse(path, f"unsupported PLY header line {line[:80]!r}: expected one "
                                    "'format ascii|binary_little_endian|binary_big_endian 1.0'")
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append(_PlyElement(words[1], _ply_count(path, words[1], words[2]), []))
        elif words[0] == "property" and elements and fmt:
            elements[-1].properties.append(_ply_property(path, words, line))
        else:
            raise _refuse(path, f"unsupported PLY header line {line[:80]!r} (Mitsuba accepts ply, format, "
                                "comment, element, property and end_header, properties after format and element)")
    if fmt is None:
        raise _refuse(path, "has no 'format' line in its PLY header")
    return fmt, elements, pos


def _ply_count(path: str, name: str, token: str) -> int:
    if not (token.isascii() and token.isdigit()) or len(token) > 20:
        raise _refuse(path, f"element {name!r}: count {token[:30]!r} must be a plain decimal number below 2^31")
    return int(token)


def _ply_property(path: str, words: list[str], line: str) -> _PlyProperty:
    if words[1] == "list" and len(words) == 5:
        count_type, item_type, name = words[2], words[3], words[4]
        for word in (count_type, item_type):
            if word not in _PLY_TYPES:
                raise _refuse(path, f"unknown PLY property type {word[:30]!r} in {line[:80]!r}; "
                                    f"known: {', '.join(_PLY_TYPES)}")
        if _PLY_TYPES[count_type][0] not in "iu":
            raise _refuse(path, f"the count of list {name!r} must have an integer type, not {count_type!r}")
        return _PlyProperty(name, _PLY_TYPES[item_type], _PLY_TYPES[count_type])
    if len(words) == 3 and words[1] != "list":
        if words[1] not in _PLY_TYPES:
            raise _refuse(path, f"unknown PLY property type {words[1][:30]!r} in {line[:80]!r}; "
                                f"known: {', '.join(_PLY_TYPES)}")
        return _PlyProperty(words[2], _PLY_TYPES[words[1]])
    raise _refuse(path, f"malformed PLY property line {line[:80]!r}")


def _describe(elements: list[_PlyElement]) -> str:
    return ", ".join(f"{e.count} {e.name!r}" for e in elements) + " elements" if elements else "no elements"


def _check_ply_binary(path: str, body: memoryview, elements: list[_PlyElement], vertices: int,
                      order: str) -> None:
    needed = sum(e.count * e.min_stride() for e in elements)
    if needed > len(body):
        raise _refuse(path, f"the PLY header declares {_describe(elements)}, which need at least {needed} bytes "
                            f"of binary data, but the file has {len(body)} after the header")
    exact = sum(e.count * e.stride() for e in elements)
    if exact != len(body):
        raise _refuse(path, f"the PLY header declares {_describe(elements)}: with triangle faces (the only "
                            f"kind Mitsuba reads) that is exactly {exact} bytes after the header, the file has "
                            f"{len(body)}")
    offset = 0
    for element in elements:
        if not any(p.count_type for p in element.properties):
            offset += element.count * element.stride()
            continue
        fields = []
        for i, p in enumerate(element.properties):
            if p.count_type:
                fields.append((f"c{i}", order + p.count_type))
                fields += [(f"l{i}_{j}", order + p.type) for j in range(3)]
            else:
                fields.append((f"s{i}", order + p.type))
        rows = np.frombuffer(body, dtype=np.dtype(fields), count=element.count, offset=offset)
        offset += element.count * element.stride()
        for i, p in enumerate(element.properties):
            if p.count_type:
                _check_lists(path, element, p, rows[f"c{i}"], [rows[f"l{i}_{j}"] for j in range(3)], vertices)


def _check_lists(path: str, element: _PlyElement, prop: _PlyProperty, counts: np.ndarray,
                 columns: list[np.ndarray], vertices: int, first_row: int = 0) -> None:
    """Every list has 3 entries; the face indices lie in [0, vertices)."""
    bad = np.flatnonzero(counts != 3)
    if bad.size:
        row = int(bad[0])
        raise _refuse(path, f"{element.name} {first_row + row}: list {prop.name!r} has {counts[row]} entries; "
                            "Mitsuba reads triangles only (3)")
    if element.name != "face" or prop.name not in _FACE_LISTS:
        return
    for column in columns:
        if column.size and (column.min() < 0 or column.max() >= vertices):
            row = int(np.flatnonzero((column < 0) | (column >= vertices))[0])
            raise _refuse(path, f"face {first_row + row}: vertex index {column[row]} is out of range (the mesh has "
                                f"{vertices} vertices)")


def _count_tokens(body: memoryview) -> int:
    """Whitespace-separated tokens in ``body``, counted in chunks with numpy."""
    raw = np.frombuffer(body, dtype=np.uint8)
    count, previous_space = 0, True
    for start in range(0, raw.size, _CHUNK):
        space = _WHITESPACE[raw[start:start + _CHUNK]]
        count += int(np.count_nonzero(space[:-1] & ~space[1:])) + int(previous_space and not space[0])
        previous_space = bool(space[-1])
    return count


def _token_offset(body: memoryview, index: int) -> int:
    """Byte offset of token ``index`` (0-based) in ``body``; len(body) if there are fewer."""
    raw = np.frombuffer(body, dtype=np.uint8)
    seen, previous_space = 0, True
    for start in range(0, raw.size, _CHUNK):
        space = _WHITESPACE[raw[start:start + _CHUNK]]
        begins = ~space & np.concatenate(([previous_space], space[:-1]))
        found = np.flatnonzero(begins)
        if seen + found.size > index:
            return start + int(found[index - seen])
        seen += found.size
        previous_space = bool(space[-1])
    return len(body)


def _check_ply_ascii(path: str, body: memoryview, elements: list[_PlyElement], vertices: int) -> None:
    tokens = _count_tokens(body)
    needed = sum(e.count * e.min_tokens() for e in elements)
    if needed > tokens:
        raise _refuse(path, f"the PLY header declares {_describe(elements)}, which need at least {needed} values, "
                            f"but the file has {tokens} after the header")
    exact = sum(e.count * e.tokens() for e in elements)
    if exact != tokens:
        raise _refuse(path, f"the PLY header declares {_describe(elements)}: with triangle faces (the only kind "
                            f"Mitsuba reads) that is exactly {exact} values after the header, the file has {tokens}")
    first = 0
    for element in elements:
        lists = [(i, p) for i, p in enumerate(element.properties) if p.count_type]
        if element.name == "face" and lists and element.count:
            _check_ascii_faces(path, body, element, lists, first, vertices)
        first += element.count * element.tokens()


def _check_ascii_faces(path: str, body: memoryview, element: _PlyElement, lists, first: int,
                       vertices: int) -> None:
    """Parse the face rows in chunks of whole tokens; check list counts and indices."""
    width = element.tokens()
    columns, column = {}, 0
    for i, p in enumerate(element.properties):
        if p.count_type:
            columns[i] = column
            column += 4
        else:
            column += 1
    start = _token_offset(body, first)
    stop = _token_offset(body, first + element.count * width)
    text = bytes(body[start:stop])
    pending = np.empty(0, dtype="S1")
    row0, pos = 0, 0
    while pos < len(text):
        end = min(pos + _CHUNK, len(text))
        while end < len(text) and not _WHITESPACE[text[end]]:
            end += 1
        words = text[pos:end].split()
        pos = end
        if not words:
            continue
        values = np.concatenate((pending, np.array(words)))
        rows = values.size // width
        block, pending = values[:rows * width].reshape(rows, width), values[rows * width:]
        for i, p in lists:
            c = columns[i]
            try:
                numbers = block[:, c:c + 4].astype(np.int64)
            except (ValueError, OverflowError):
                raise _refuse(path, f"face list {p.name!r}: counts and indices must be integers") from None
            _check_lists(path, element, p, numbers[:, 0], [numbers[:, j] for j in (1, 2, 3)], vertices, row0)
        row0 += rows


# ------------------------------------------------------------------------------------------ OBJ

_OBJ_VERTEX = re.compile(rb"^[ \t\r]*v[ \t]", re.MULTILINE)
_OBJ_FACE = re.compile(rb"^[ \t\r]*f[ \t]([^\n]*)", re.MULTILINE)


def _check_obj(path: str, data: memoryview, limits) -> MeshSummary:
    """Count ``v`` lines and the triangles of ``f`` lines (n corners -> n - 2), as Mitsuba's
    reader recognizes them (a line's first word after spaces, tabs and carriage returns)."""
    text = bytes(data)
    vertices = sum(1 for _ in _OBJ_VERTEX.finditer(text))
    _check_count(path, "vertices ('v' lines)", vertices, limits.max_mesh_vertices, "max_mesh_vertices", "has")
    faces = 0
    cap = min(limits.max_mesh_faces, MAX_MESH_COUNT)
    for match in _OBJ_FACE.finditer(text):
        faces += max(len(match[1].split()) - 2, 0)
        if faces > cap:
            raise _refuse(path, f"has more than {cap} triangles (faces with n corners count n - 2); at most "
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
                data = self._source[self._taken:self._taken + _CHUNK]
                self._taken += len(data)
            out = self._zlib.decompress(data, want)
            if out:
                self.produced += len(out)
                return out
        return b""

    def chunks(self, size: int, chunk: int = _CHUNK) -> Iterator[bytes]:
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
        raise _refuse(path, "is too short to be a Mitsuba serialized mesh")
    magic, version = struct.unpack_from("<HH", data, 0)
    if magic != _SERIALIZED_MAGIC or version not in (3, 4):
        raise _refuse(path, "is not a Mitsuba serialized mesh (expected identifier 0x041C, version 3 or 4)")
    offsets, table = _serialized_offsets(path, data, version)
    used = 0
    shapes = []
    for index, offset in enumerate(offsets):
        end = offsets[index + 1] if index + 1 < len(offsets) else table
        if struct.unpack_from("<HH", data, offset) != (magic, version):
            raise _refuse(path, f"shape {index} at offset {offset} does not start with the file's header")
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
        raise _refuse(path, f"has an invalid end-of-file shape table: {count} shapes do not fit in "
                            f"{len(data)} bytes")
    offsets = list(struct.unpack_from(f"<{count}{'Q' if width == 8 else 'I'}", data, table))
    if offsets[0] != 0 or any(b - a < 6 for a, b in itertools.pairwise(offsets)) or table - offsets[-1] < 6:
        raise _refuse(path, "has an invalid end-of-file shape table: offsets must start at 0, increase, "
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
                raise _refuse(path, f"{where}: the shape name is longer than {_SERIALIZED_NAME_BYTES} bytes")
        vertices, faces = struct.unpack("<QQ", inflater.read(16))
    except EOFError:
        raise _refuse(path, f"{where}: the compressed stream ends inside the mesh header") from None
    except zlib.error as exc:
        raise _refuse(path, f"{where}: invalid compressed data ({exc})") from None
    _check_count(path, f"vertices in {where}", vertices, limits.max_mesh_vertices, "max_mesh_vertices")
    _check_count(path, f"faces in {where}", faces, limits.max_mesh_faces, "max_mesh_faces")
    real = 8 if flags & _DOUBLE else 4
    per_vertex = 3 + 3 * bool(flags & _HAS_NORMALS) + 2 * bool(flags & _HAS_TEXCOORDS) + 3 * bool(flags & _HAS_COLORS)
    arrays = vertices * per_vertex * real
    total = inflater.produced + arrays + faces * 12
    if used + total > limits.max_mesh_decompressed_bytes:
        before = f" ({used + total} with the shapes before it)" if used else ""
        raise _refuse(path, f"{where}: {vertices} vertices and {faces} faces decompress to {total} bytes{before}; "
                            f"at most {limits.max_mesh_decompressed_bytes} bytes per file are allowed "
                            "(max_mesh_decompressed_bytes)")
    try:
        for _ in inflater.chunks(arrays):
            pass
        for piece in inflater.chunks(faces * 12, _CHUNK - _CHUNK % 12):
            indices = np.frombuffer(piece, dtype="<u4")
            if indices.max() >= vertices:
                raise _refuse(path, f"{where}: face index {int(indices.max())} is out of range (the shape has "
                                    f"{vertices} vertices)")
    except EOFError:
        raise _refuse(path, f"{where}: declares {vertices} vertices and {faces} faces ({total} bytes), but its "
                            f"compressed stream ends after {inflater.produced} bytes") from None
    except zlib.error as exc:
        raise _refuse(path, f"{where}: invalid compressed data ({exc})") from None
    return MeshSummary("serialized", vertices, faces, len(stream) + 4), inflater.produced

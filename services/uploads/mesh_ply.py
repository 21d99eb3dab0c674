"""PLY files (binary and ASCII) checked before Mitsuba reads them: the rules are in
:mod:`services.uploads.meshes`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.uploads.mesh_base import CHUNK, MAX_COUNT, MeshSummary, check_count, refuse

_PLY_HEADER_BYTES = 64 << 10  # a real PLY header is a few hundred bytes

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


def check_ply(path: str, data: memoryview, limits) -> MeshSummary:
    fmt, elements, start = _ply_header(path, data)
    for element in elements:
        if element.name == "vertex":
            check_count(path, "vertices", element.count, limits.max_mesh_vertices, "max_mesh_vertices")
        elif element.name == "face":
            check_count(path, "faces", element.count, limits.max_mesh_faces, "max_mesh_faces")
        else:
            check_count(path, f"'{element.name}' elements", element.count, MAX_COUNT, "2^31")
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
        raise refuse(path, "is not a PLY file: it must start with a 'ply' line")
    fmt = None
    elements: list[_PlyElement] = []
    pos = first + 1
    while True:
        end = head.find(b"\n", pos)
        if end < 0:
            raise refuse(path, f"has no 'end_header' line in its first {_PLY_HEADER_BYTES} bytes")
        try:
            words = head[pos:end].decode("ascii").split()
        except UnicodeDecodeError:
            raise refuse(path, "has a PLY header that is not ASCII text") from None
        line, pos = " ".join(words), end + 1
        if not words or words[0] == "comment":
            continue
        if words[0] == "end_header" and len(words) == 1:
            break
        if words[0] == "format":
            if fmt or len(words) != 3 or words[2] != "1.0" or \
                    words[1] not in ("ascii", "binary_little_endian", "binary_big_endian"):
                raise refuse(path, f"unsupported PLY header line {line[:80]!r}: expected one "
                                    "'format ascii|binary_little_endian|binary_big_endian 1.0'")
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3:
            elements.append(_PlyElement(words[1], _ply_count(path, words[1], words[2]), []))
        elif words[0] == "property" and elements and fmt:
            elements[-1].properties.append(_ply_property(path, words, line))
        else:
            raise refuse(path, f"unsupported PLY header line {line[:80]!r} (Mitsuba accepts ply, format, "
                                "comment, element, property and end_header, properties after format and element)")
    if fmt is None:
        raise refuse(path, "has no 'format' line in its PLY header")
    return fmt, elements, pos


def _ply_count(path: str, name: str, token: str) -> int:
    if not (token.isascii() and token.isdigit()) or len(token) > 20:
        raise refuse(path, f"element {name!r}: count {token[:30]!r} must be a plain decimal number below 2^31")
    return int(token)


def _ply_property(path: str, words: list[str], line: str) -> _PlyProperty:
    if words[1] == "list" and len(words) == 5:
        count_type, item_type, name = words[2], words[3], words[4]
        for word in (count_type, item_type):
            if word not in _PLY_TYPES:
                raise refuse(path, f"unknown PLY property type {word[:30]!r} in {line[:80]!r}; "
                                    f"known: {', '.join(_PLY_TYPES)}")
        if _PLY_TYPES[count_type][0] not in "iu":
            raise refuse(path, f"the count of list {name!r} must have an integer type, not {count_type!r}")
        return _PlyProperty(name, _PLY_TYPES[item_type], _PLY_TYPES[count_type])
    if len(words) == 3 and words[1] != "list":
        if words[1] not in _PLY_TYPES:
            raise refuse(path, f"unknown PLY property type {words[1][:30]!r} in {line[:80]!r}; "
                                f"known: {', '.join(_PLY_TYPES)}")
        return _PlyProperty(words[2], _PLY_TYPES[words[1]])
    raise refuse(path, f"malformed PLY property line {line[:80]!r}")


def _describe(elements: list[_PlyElement]) -> str:
    return ", ".join(f"{e.count} {e.name!r}" for e in elements) + " elements" if elements else "no elements"


def _check_ply_binary(path: str, body: memoryview, elements: list[_PlyElement], vertices: int,
                      order: str) -> None:
    needed = sum(e.count * e.min_stride() for e in elements)
    if needed > len(body):
        raise refuse(path, f"the PLY header declares {_describe(elements)}, which need at least {needed} bytes "
                            f"of binary data, but the file has {len(body)} after the header")
    exact = sum(e.count * e.stride() for e in elements)
    if exact != len(body):
        raise refuse(path, f"the PLY header declares {_describe(elements)}: with triangle faces (the only "
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
        raise refuse(path, f"{element.name} {first_row + row}: list {prop.name!r} has {counts[row]} entries; "
                            "Mitsuba reads triangles only (3)")
    if element.name != "face" or prop.name not in _FACE_LISTS:
        return
    for column in columns:
        if column.size and (column.min() < 0 or column.max() >= vertices):
            row = int(np.flatnonzero((column < 0) | (column >= vertices))[0])
            raise refuse(path, f"face {first_row + row}: vertex index {column[row]} is out of range (the mesh has "
                                f"{vertices} vertices)")


def _count_tokens(body: memoryview) -> int:
    """Whitespace-separated tokens in ``body``, counted in chunks with numpy."""
    raw = np.frombuffer(body, dtype=np.uint8)
    count, previous_space = 0, True
    for start in range(0, raw.size, CHUNK):
        space = _WHITESPACE[raw[start:start + CHUNK]]
        count += int(np.count_nonzero(space[:-1] & ~space[1:])) + int(previous_space and not space[0])
        previous_space = bool(space[-1])
    return count


def _token_offset(body: memoryview, index: int) -> int:
    """Byte offset of token ``index`` (0-based) in ``body``; len(body) if there are fewer."""
    raw = np.frombuffer(body, dtype=np.uint8)
    seen, previous_space = 0, True
    for start in range(0, raw.size, CHUNK):
        space = _WHITESPACE[raw[start:start + CHUNK]]
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
        raise refuse(path, f"the PLY header declares {_describe(elements)}, which need at least {needed} values, "
                            f"but the file has {tokens} after the header")
    exact = sum(e.count * e.tokens() for e in elements)
    if exact != tokens:
        raise refuse(path, f"the PLY header declares {_describe(elements)}: with triangle faces (the only kind "
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
        end = min(pos + CHUNK, len(text))
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
                raise refuse(path, f"face list {p.name!r}: counts and indices must be integers") from None
            _check_lists(path, element, p, numbers[:, 0], [numbers[:, j] for j in (1, 2, 3)], vertices, row0)
        row0 += rows

"""Files the upload tests build (meshes, images, in the formats Mitsuba reads), in one place."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
from PIL import Image

QUAD = np.array([[-1, 0, -1], [1, 0, -1], [1, 0, 1], [-1, 0, 1]], dtype=np.float32)
TRIANGLES = np.array([[0, 2, 1], [0, 3, 2]], dtype=np.uint32)


def ply_header(fmt: str, vertices: int, faces: int, extra: str = "") -> bytes:
    return (f"ply\nformat {fmt} 1.0\ncomment made by a test\nelement vertex {vertices}\n"
            "property float x\nproperty float y\nproperty float z\n"
            f"element face {faces}\nproperty list uchar int vertex_indices\n{extra}end_header\n").encode()


def ply_binary(points=QUAD, triangles=TRIANGLES, order: str = "<", vertices=None, faces=None) -> bytes:
    fmt = "binary_little_endian" if order == "<" else "binary_big_endian"
    rows = np.zeros(len(triangles), dtype=[("n", "u1"), ("i", order + "i4", 3)])
    rows["n"], rows["i"] = 3, triangles
    header = ply_header(fmt, len(points) if vertices is None else vertices, len(triangles) if faces is None else faces)
    return header + points.astype(order + "f4").tobytes() + rows.tobytes()


def ply_ascii(points=QUAD, triangles=TRIANGLES, vertices=None, faces=None) -> bytes:
    body = "".join(" ".join(map(str, p)) + "\n" for p in points.tolist())
    body += "".join(f"{len(t)} " + " ".join(map(str, t)) + "\n" for t in triangles.tolist())
    return ply_header("ascii", len(points) if vertices is None else vertices,
                      len(triangles) if faces is None else faces) + body.encode()


OBJ = b"# quad\nv -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nvt 0 0\nvn 0 1 0\nf 1/1/1 3/1/1 2/1/1\n  f 1 4 3 \n"


def serialized_shape(points=QUAD, triangles=TRIANGLES, flags: int = 0x1000, name: bytes = b"quad",
                     vertices=None, faces=None, tail: bytes = b"", version: int = 4) -> bytes:
    """One shape per Mitsuba's format description: uint16 0x041C, uint16 version, then a zlib
    stream of flags, the name (version 4), uint64 counts, positions, faces."""
    payload = struct.pack("<I", flags) + (name + b"\0" if version == 4 else b"")
    payload += struct.pack("<QQ", len(points) if vertices is None else vertices,
                           len(triangles) if faces is None else faces)
    payload += points.astype("<f4").tobytes() + triangles.astype("<u4").tobytes() + tail
    return struct.pack("<HH", 0x041C, version) + zlib.compress(payload)


def serialized(*shapes: bytes, version: int = 4) -> bytes:
    offsets, position = [], 0
    for shape in shapes:
        offsets.append(position)
        position += len(shape)
    table = struct.pack(f"<{len(offsets)}{'Q' if version == 4 else 'I'}", *offsets)
    return b"".join(shapes) + table + struct.pack("<I", len(shapes))


def png(width: int, height: int, mode: str = "RGB") -> bytes:
    buffer = io.BytesIO()
    Image.new(mode, (width, height)).save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def jpeg(width: int, height: int) -> bytes:
    buffer = io.BytesIO()
    Image.new("RGB", (width, height), (200, 10, 10)).save(buffer, format="JPEG")
    return buffer.getvalue()


def npy(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def exr_header(width: int, height: int, channels: str | list[str] = "BGR", flags: int = 0) -> bytes:
    """A scanline OpenEXR header per the file layout: magic, version, attributes, terminator
    (``channels``: their names, one letter each or a list)."""
    def attribute(name: str, kind: str, value: bytes) -> bytes:
        return name.encode() + b"\0" + kind.encode() + b"\0" + struct.pack("<i", len(value)) + value

    chlist = b"".join(c.encode() + b"\0" + struct.pack("<iB3xii", 1, 0, 1, 1) for c in channels) + b"\0"
    return (b"\x76\x2f\x31\x01" + struct.pack("<I", 2 | flags)
            + attribute("channels", "chlist", chlist)
            + attribute("compression", "compression", b"\x03")
            + attribute("dataWindow", "box2i", struct.pack("<iiii", 0, 0, width - 1, height - 1))
            + attribute("displayWindow", "box2i", struct.pack("<iiii", 0, 0, width - 1, height - 1))
            + attribute("lineOrder", "lineOrder", b"\x00")
            + attribute("pixelAspectRatio", "float", struct.pack("<f", 1.0))
            + b"\0")

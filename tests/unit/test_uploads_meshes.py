"""Checks of uploaded meshes before Mitsuba reads them (no Mitsuba needed)."""

from __future__ import annotations

import struct
import zlib

import numpy as np
import pytest

from services.uploads import meshes
from services.uploads.meshes import MeshLimits, MeshSummary, check_mesh
from services.uploads.scene import InvalidJob
from tests.support.payloads import OBJ, QUAD, TRIANGLES, ply_ascii, ply_binary, ply_header, serialized, serialized_shape

DEFAULTS = MeshLimits()


def refused(path: str, data: bytes, limits: MeshLimits = DEFAULTS, kind: str | None = None) -> str:
    with pytest.raises(InvalidJob) as caught:
        check_mesh(path, data, limits, kind=kind)
    assert caught.value.field == f"scene.files[{path}]"
    return caught.value.message


# ---------------------------------------------------------------------------------- valid files

@pytest.mark.parametrize("path, data, fmt", [
    ("m.ply", ply_binary(), "ply"),
    ("m.ply", ply_binary(order=">"), "ply"),
    ("m.ply", ply_ascii(), "ply"),
    ("m.obj", OBJ, "obj"),
    ("m.serialized", serialized(serialized_shape()), "serialized"),
    ("m.serialized", serialized(serialized_shape(version=3), version=3), "serialized"),
], ids=["ply little endian", "ply big endian", "ply ascii", "obj", "serialized v4", "serialized v3"])
def test_valid_meshes_are_summarized(path, data, fmt):
    summary = check_mesh(path, data)
    assert (summary.format, summary.vertices, summary.faces, summary.bytes) == (fmt, 4, 2, len(data))


def test_polygons_count_as_the_triangles_mitsuba_makes():
    obj = b"v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0 2 0\nf 1 2 3 4 5\nf 1 2 3\n"
    assert check_mesh("p.obj", obj) == MeshSummary("obj", 5, 4, len(obj))


def test_serialized_shapes_are_summarized_one_by_one():
    one, two = serialized_shape(), serialized_shape(QUAD[:3], TRIANGLES[:1], flags=0x1000, name=b"tri")
    summary = check_mesh("s.serialized", serialized(one, two))
    assert (summary.vertices, summary.faces, len(summary.shapes)) == (7, 3, 2)
    assert summary.shape(1) == MeshSummary("serialized", 3, 1, len(two))


def test_shape_type_decides_over_the_extension():
    assert check_mesh("mesh.bin", ply_binary(), kind="ply").format == "ply"
    assert "is not a PLY file" in refused("mesh.obj", OBJ, kind="ply")
    assert "is not a mesh Mitsuba can read" in refused("mesh.bin", OBJ)


def test_ply_with_extra_attributes_and_elements_is_accepted():
    extra = "element edge 1\nproperty int a\nproperty int b\n"
    data = ply_header("binary_little_endian", 4, 2, extra).replace(
        b"property float z\n", b"property float z\nproperty uchar red\nproperty double u\n")
    rows = np.zeros(4, dtype=[("p", "<f4", 3), ("r", "u1"), ("u", "<f8")])
    rows["p"] = QUAD
    faces = np.zeros(2, dtype=[("n", "u1"), ("i", "<i4", 3)])
    faces["n"], faces["i"] = 3, TRIANGLES
    data += rows.tobytes() + faces.tobytes() + struct.pack("<ii", 0, 1)
    assert check_mesh("m.ply", data).vertices == 4


# ---------------------------------------------------------------------------------------- PLY

def test_ply_vertex_count_past_32_bits_is_refused():
    """The issue's attack: 2^32 + 1 vertices truncate to 1 in Mitsuba, which then overflows."""
    message = refused("meshes/m.ply", ply_binary(vertices=4294967297))
    assert message == "declares 4294967297 vertices; counts must be below 2^31"


@pytest.mark.parametrize("count", ["-1", "+4", "4abc", "0x10", "9" * 30])
def test_ply_counts_must_be_plain_decimals(count):
    data = ply_binary().replace(b"element vertex 4", f"element vertex {count}".encode())
    assert "must be a plain decimal number below 2^31" in refused("m.ply", data)


def test_ply_counts_are_capped():
    limits = MeshLimits(max_mesh_vertices=3, max_mesh_faces=1)
    assert refused("m.ply", ply_binary(), limits) == "declares 4 vertices; at most 3 are allowed per mesh " \
                                                     "(max_mesh_vertices)"
    limits = MeshLimits(max_mesh_faces=1)
    assert "declares 2 faces; at most 1 are allowed per mesh (max_mesh_faces)" in refused("m.ply", ply_binary(),
                                                                                          limits)


def test_caps_never_exceed_what_mitsuba_can_size():
    limits = MeshLimits(max_mesh_vertices=2**40)
    message = refused("m.ply", ply_binary(vertices=2**31 - 1), limits)
    assert f"at most {(2**32 - 1) // 3} are allowed per mesh" in message


def test_binary_ply_body_shorter_than_declared_is_refused():
    data = ply_binary(vertices=1000)
    message = refused("m.ply", data)
    assert "declares 1000 'vertex', 2 'face' elements, which need at least 12002 bytes of binary data, but the " \
           "file has 74 after the header" in message


def test_binary_ply_with_trailing_or_missing_bytes_is_refused():
    assert "exactly 74 bytes after the header, the file has 75" in refused("m.ply", ply_binary() + b"\0")
    assert "exactly 74 bytes after the header, the file has 70" in refused("m.ply", ply_binary()[:-4])


def test_binary_ply_quads_are_refused():
    rows = np.zeros(2, dtype=[("n", "u1"), ("i", "<i4", 3)])
    rows["n"], rows["i"] = 3, TRIANGLES
    data = bytearray(ply_binary())
    data[-len(rows.tobytes()) // 2] = 4  # the second face's count byte
    assert "face 1: list 'vertex_indices' has 4 entries; Mitsuba reads triangles only" in refused("m.ply", data)


@pytest.mark.parametrize("bad", [4, -1, 2**31 - 1])
def test_binary_ply_face_indices_out_of_range_are_refused(bad):
    triangles = TRIANGLES.astype(np.int64)
    triangles[1, 2] = bad
    data = ply_binary(triangles=triangles.astype(np.uint32))
    message = refused("m.ply", data)
    assert message == f"face 1: vertex index {bad} is out of range (the mesh has 4 vertices)"


def test_ascii_ply_lying_about_counts_is_refused():
    message = refused("m.ply", ply_ascii(vertices=1_000_000))
    assert "declares 1000000 'vertex', 2 'face' elements, which need at least 3000002 values, but the file has 20" \
           in message
    message = refused("m.ply", ply_ascii(faces=1))
    assert "exactly 16 values after the header, the file has 20" in message


def test_ascii_ply_face_indices_are_checked():
    triangles = TRIANGLES.copy()
    triangles[0, 1] = 7
    assert refused("m.ply", ply_ascii(triangles=triangles)) == \
        "face 0: vertex index 7 is out of range (the mesh has 4 vertices)"
    data = ply_ascii().replace(b"3 0 3 2", b"3 0 3 2.5")
    assert "counts and indices must be integers" in refused("m.ply", data)


def test_ascii_ply_face_rows_across_parse_chunks(monkeypatch):
    from services.uploads import mesh_ply

    monkeypatch.setattr(mesh_ply, "CHUNK", 7)  # rows and tokens straddle chunk boundaries
    points = np.zeros((50, 3), dtype=np.float32)
    triangles = np.array([[i, i + 1, i + 2] for i in range(48)], dtype=np.uint32)
    assert check_mesh("m.ply", ply_ascii(points, triangles)).faces == 48
    triangles[45, 0] = 50
    assert refused("m.ply", ply_ascii(points, triangles)).startswith("face 45: vertex index 50 is out of range")


@pytest.mark.parametrize("line, fragment", [
    ("property int128 w", "unknown PLY property type 'int128'"),
    ("property list float int vertex_indices", "must have an integer type"),
    ("property list uchar quad vertex_indices", "unknown PLY property type 'quad'"),
    ("obj_info generated", "unsupported PLY header line 'obj_info generated'"),
], ids=["scalar type", "list count type", "list item type", "unknown line"])
def test_unknown_ply_header_lines_and_types_are_refused(line, fragment):
    data = ply_binary().replace(b"end_header", line.encode() + b"\nend_header")
    assert fragment in refused("m.ply", data)


def test_ply_without_end_header_is_refused():
    assert "has no 'end_header' line" in refused("m.ply", b"ply\nformat ascii 1.0\n" + b"comment x\n" * 10000)
    assert "unsupported PLY header line 'format ascii 2.0'" in refused("m.ply", b"ply\nformat ascii 2.0\n")


# ---------------------------------------------------------------------------------------- OBJ

def test_obj_counts_are_capped():
    polygon = b"v 0 0 0\n" * 3 + b"f " + b"1 " * 400 + b"\n"  # one face line, 398 triangles
    message = refused("m.obj", polygon * 3, MeshLimits(max_mesh_faces=1000))
    assert message == "has more than 1000 triangles (faces with n corners count n - 2); at most 1000 are allowed " \
                      "per mesh (max_mesh_faces)"
    message = refused("m.obj", b"v 0 0 0\n" * 11, MeshLimits(max_mesh_vertices=10))
    assert message == "has 11 vertices ('v' lines); at most 10 are allowed per mesh (max_mesh_vertices)"


# --------------------------------------------------------------------------------- serialized

def test_serialized_zlib_bomb_is_refused_before_inflating():
    """A few KB whose header declares 10 M vertices with normals, texcoords and colors in double
    precision (880 MB): refused from the declared sizes, nothing past the header is inflated."""
    flags = 0x2000 | 0x1 | 0x2 | 0x8
    shape = serialized_shape(QUAD[:0], TRIANGLES[:0], flags=flags, vertices=10_000_000, faces=1,
                             tail=bytes(8 << 20))
    data = serialized(shape)
    assert len(data) < 20_000
    message = refused("bomb.serialized", data)
    assert "shape 0: 10000000 vertices and 1 faces decompress to 880000037 bytes; at most 268435456 bytes per " \
           "file are allowed (max_mesh_decompressed_bytes)" in message


def test_serialized_inflates_only_what_its_counts_need(monkeypatch):
    """Small counts and a 32 MB tail of zeros: accepted, and at most the declared bytes are
    inflated (the tail is never decompressed)."""
    produced = []
    real = zlib.decompressobj

    class Counting:
        def __init__(self):
            self._d = real()

        def decompress(self, data, max_length=0):
            out = self._d.decompress(data, max_length)
            produced.append(len(out))
            return out

        def __getattr__(self, name):
            return getattr(self._d, name)

    data = serialized(serialized_shape(tail=bytes(32 << 20)))
    monkeypatch.setattr(meshes.zlib, "decompressobj", Counting)
    assert check_mesh("m.serialized", data).vertices == 4
    assert sum(produced) == 4 + 5 + 16 + 4 * 12 + 2 * 12


def test_serialized_decompressed_size_is_capped_across_shapes():
    data = serialized(serialized_shape(), serialized_shape())
    limits = MeshLimits(max_mesh_decompressed_bytes=120)
    assert "shape 1: 4 vertices and 2 faces decompress to 97 bytes (194 with the shapes before it); at most 120" \
           in refused("m.serialized", data, limits)


def test_serialized_counts_are_checked():
    data = serialized(serialized_shape(vertices=2**32 + 4))
    assert refused("m.serialized", data) == "declares 4294967300 vertices in shape 0; counts must be below 2^31"
    data = serialized(serialized_shape(faces=3))
    assert "shape 0: declares 4 vertices and 3 faces (109 bytes), but its compressed stream ends after 97 bytes" \
           in refused("m.serialized", data)


def test_serialized_face_indices_are_checked():
    triangles = TRIANGLES.copy()
    triangles[1, 1] = 4
    assert refused("m.serialized", serialized(serialized_shape(triangles=triangles))) == \
        "shape 0: face index 4 is out of range (the shape has 4 vertices)"


@pytest.mark.parametrize("data, fragment", [
    (b"\x1c\x04\x05\x00" + bytes(20), "expected identifier 0x041C, version 3 or 4"),
    (serialized_shape() + struct.pack("<QI", 0, 2), "invalid end-of-file shape table"),
    (serialized_shape() + struct.pack("<QI", 8, 1), "offsets must start at 0"),
    (serialized_shape(), "invalid end-of-file shape table"),
    (serialized(serialized_shape()[:12]), "the compressed stream ends inside the mesh header"),
    (serialized(struct.pack("<HH", 0x041C, 4) + b"not zlib data at all"), "invalid compressed data"),
    (serialized(serialized_shape(name=b"n" * 5000)), "the shape name is longer than 4096 bytes"),
], ids=["version", "count", "first offset", "no table", "truncated", "not zlib", "long name"])
def test_malformed_serialized_files_are_refused(data, fragment):
    assert fragment in refused("m.serialized", data)

"""The checks of uploaded Mitsuba XML scenes (no Mitsuba needed)."""

from __future__ import annotations

import base64
import io
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from services.uploads.pack import pack_scene
from services.uploads.scene import (
    MAX_INCLUDE_EXPANSIONS,
    InvalidJob,
    UploadLimits,
    check_scene_upload,
    scene_references,
)

OBJ_QUAD = b"v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 3 2\nf 1 4 3\n"
MATERIALS = '<scene version="3.0.0"><bsdf type="diffuse" id="paint"/></scene>'
MAIN = """<scene version="3.0.0">
    <include filename="fragments/materials.xml"/>
    <shape type="obj" id="floor">
        <string name="filename" value="meshes/quad.obj"/>
        <ref id="paint"/>
    </shape>
</scene>"""


def b64(data: str | bytes) -> str:
    return base64.b64encode(data.encode() if isinstance(data, str) else data).decode("ascii")


def scene(*body: str) -> str:
    return '<scene version="3.0.0">' + "".join(body) + "</scene>"


def valid_files(**extra: str | bytes) -> dict[str, str]:
    files = {"fragments/materials.xml": MATERIALS, "meshes/quad.obj": OBJ_QUAD, **extra}
    return {path: b64(data) for path, data in files.items()}


def mesh(filename: str) -> str:
    return f'<shape type="obj"><string name="filename" value="{filename}"/></shape>'


def test_valid_scene_returns_the_decoded_files():
    decoded = check_scene_upload(MAIN, valid_files())
    assert decoded == {"fragments/materials.xml": MATERIALS.encode(), "meshes/quad.obj": OBJ_QUAD}


def test_unreferenced_files_are_not_checked():
    unused = scene('<path value="/etc"/>')
    decoded = check_scene_upload(MAIN, valid_files(**{"unused.xml": unused}))
    assert decoded["unused.xml"] == unused.encode()


def test_shared_fragments_and_spectrum_files_are_accepted():
    main = scene('<include filename="a.xml"/><include filename="b.xml"/>',
                 '<bsdf type="conductor"><spectrum name="eta" filename="spectra/eta.spd"/></bsdf>')
    files = {"a.xml": scene('<include filename="common.xml"/>'), "b.xml": scene('<include filename="common.xml"/>'),
             "common.xml": scene(mesh("meshes/quad.obj")), "meshes/quad.obj": OBJ_QUAD, "spectra/eta.spd": "400 1\n"}
    assert set(check_scene_upload(main, {p: b64(d) for p, d in files.items()})) == set(files)


def test_scene_references_lists_includes_and_files_in_document_order():
    xml = scene('<include filename="b.xml"/>', mesh("m.obj"), '<spectrum name="eta" filename="e.spd"/>',
                '<include filename="a.xml"/>')
    assert scene_references(xml) == (["b.xml", "a.xml"], ["m.obj", "e.spd"])


def test_error_names_field_and_message():
    error = InvalidJob("scene.xml", "bad")
    assert (error.field, error.message, str(error)) == ("scene.xml", "bad", "scene.xml: bad")
    assert isinstance(error, ValueError)


XXE = '<?xml version="1.0"?><!DOCTYPE scene [<!ENTITY xxe SYSTEM "file:///etc/passwd">]><scene>&xxe;</scene>'
LAUGHS = ('<?xml version="1.0"?><!DOCTYPE lolz [<!ENTITY lol "lol">'
          + "".join(f'<!ENTITY lol{i} "{("&lol" + str(i - 1) + ";") * 10}">' for i in range(1, 10))
          + ']><scene version="3.0.0">&lol9;</scene>').replace("&lol0;", "&lol;")
CYCLE = {"a.xml": scene('<include filename="b.xml"/>'), "b.xml": scene('<include filename="a.xml"/>')}
CHAIN = {f"c{i}.xml": scene(f'<include filename="c{i + 1}.xml"/>') for i in range(20)} | {"c20.xml": scene()}
BOMB = {f"d{i}.xml": scene(f'<include filename="d{i + 1}.xml"/>' * 2) for i in range(12)} | {"d12.xml": scene()}

MALICIOUS = {
    # keys of `files`
    "absolute key": (MAIN, {"/etc/passwd": "eA=="}, "scene.files[/etc/passwd]", "no leading '/'"),
    "dotdot key": (MAIN, {"../secret.obj": "eA=="}, "scene.files[../secret.obj]", "no '..'"),
    "empty component": (MAIN, {"meshes//a.obj": "eA=="}, "scene.files[meshes//a.obj]", "no '//'"),
    "dot component": (MAIN, {"./a.obj": "eA=="}, "scene.files[./a.obj]", "normalized"),
    "backslash key": (MAIN, {"meshes\\a.obj": "eA=="}, "scene.files[meshes\\a.obj]", "no backslashes"),
    "drive letter": (MAIN, {"C:/a.obj": "eA=="}, "scene.files[C:/a.obj]", "no drive letters"),
    "home key": (MAIN, {"~/a.obj": "eA=="}, "scene.files[~/a.obj]", "must not start with '~'"),
    "control key": (MAIN, {"a\x00.obj": "eA=="}, "scene.files[a\x00.obj]", "control characters"),
    "long key": (MAIN, {"a" * 256: "eA=="}, f"scene.files[{'a' * 256}]", "1 to 255 characters"),
    "plugin upload": (MAIN, {"plugins/evil.so": "eA=="}, "scene.files[plugins/evil.so]", "reserved"),
    "main name": (MAIN, {"scene.xml": "eA=="}, "scene.files[scene.xml]", "reserved for the main document"),
    "file and folder": (MAIN, {"a": "eA==", "a/b.obj": "eA=="}, "scene.files[a/b.obj]", "'a' is uploaded as a file"),
    "bad base64": (MAIN, {"meshes/quad.obj": "not base64!"}, "scene.files[meshes/quad.obj]", "not valid base64"),
    # includes
    "include absolute": (scene('<include filename="/etc/passwd"/>'), {}, "scene.xml", "no leading '/'"),
    "include dotdot": (scene('<include filename="../secret.xml"/>'), {}, "scene.xml", "no '..'"),
    "include missing": (scene('<include filename="x.xml"/>'), valid_files(), "scene.xml",
                        "include 'x.xml' is not among the uploaded files; uploaded: fragments/materials.xml, "
                        "meshes/quad.obj"),
    "include substitution": (scene('<include filename="$f"/>'), {}, "scene.xml", "substitution ($) is not allowed"),
    "include cycle": (scene('<include filename="a.xml"/>'), {p: b64(d) for p, d in CYCLE.items()},
                      "scene.files[b.xml]", "include cycle: scene.xml -> a.xml -> b.xml -> a.xml"),
    "nested include": (scene('<include filename="f/a.xml"/>'),
                       {"f/a.xml": b64(scene('<include filename="b.xml"/>')), "b.xml": b64(scene())},
                       "scene.files[f/a.xml]", "only XML files at the top of the scene folder"),
    "include depth": (scene('<include filename="c0.xml"/>'), {p: b64(d) for p, d in CHAIN.items()},
                      "scene.files[c13.xml]", "nested deeper than 15"),
    "include bomb": (scene('<include filename="d0.xml"/>'), {p: b64(d) for p, d in BOMB.items()},
                     "scene.files[d", f"more than {MAX_INCLUDE_EXPANSIONS} includes"),
    # <path>, in the main document or in an included fragment
    "path element": (scene('<path value="/etc"/>'), {}, "scene.xml", "<path> is not allowed"),
    "path in fragment": (MAIN, valid_files(**{"fragments/materials.xml": scene('<path value="."/>')}),
                         "scene.files[fragments/materials.xml]", "<path> is not allowed"),
    # file references
    "filename absolute": (scene(mesh("/etc/passwd")), {}, "scene.xml",
                          "file path '/etc/passwd' must be relative to the scene (no leading '/')"),
    "filename substitution": (scene('<default name="m" value="quad"/>', mesh("meshes/$m.obj")), valid_files(),
                              "scene.xml", "substitution ($) is not allowed in file names"),
    "filename missing": (scene(mesh("meshes/other.obj")), valid_files(), "scene.xml",
                         "file 'meshes/other.obj' is not among the uploaded files"),
    "filename no value": (scene('<shape type="obj"><string name="filename"/></shape>'), {}, "scene.xml",
                          "must have 1 to 255"),
    "spectrum outside": (scene('<bsdf type="conductor"><spectrum name="eta" filename="../x.spd"/></bsdf>'), {},
                         "scene.xml", "no '..'"),
    "spectrum absolute": (scene('<spectrum name="eta" filename="/usr/share/x.spd"/>'), {}, "scene.xml",
                          "no leading '/'"),
    "fragment reference": (MAIN, valid_files(**{"fragments/materials.xml": scene(mesh("/etc/passwd"))}),
                           "scene.files[fragments/materials.xml]", "no leading '/'"),
    # substitution, plugin types, host paths anywhere
    "substituted name": (scene('<default name="n" value="filename"/>',
                               '<shape type="obj"><string name="$n" value="secret.obj"/></shape>'), {},
                         "scene.xml", "not allowed in 'name' attributes"),
    "substituted path": (scene('<default name="up" value=".."/>',
                               '<bsdf type="conductor"><string name="material" value="$up/$up/x"/></bsdf>'), {},
                         "scene.xml", "'/' is not allowed in a value that uses or defines a substitution"),
    "slash in default": (scene('<default name="d" value="a/b"/>'), {}, "scene.xml", "'/' is not allowed"),
    "plugin type": (scene('<bsdf type="../evil"/>'), {}, "scene.xml", "plugin type must be a plain name"),
    "host path value": (scene('<bsdf type="conductor"><string name="material" value="../../etc/x"/></bsdf>'), {},
                        "scene.xml", "<string value='../../etc/x'>: attribute values must not be absolute host"),
    "absolute value": (scene('<integrator type="path" id="/etc/passwd"/>'), {}, "scene.xml",
                       "<integrator id='/etc/passwd'>: attribute values must not be absolute host paths"),
    # XML itself
    "doctype": ('<!DOCTYPE scene SYSTEM "scene.dtd"><scene/>', {}, "scene.xml", "DTD and entities are not allowed"),
    "external entity": (XXE, {}, "scene.xml", "DTD and entities are not allowed"),
    "billion laughs": (LAUGHS, {}, "scene.xml", "DTD and entities are not allowed"),
    "entity in fragment": (MAIN, valid_files(**{"fragments/materials.xml": XXE}),
                           "scene.files[fragments/materials.xml]", "DTD and entities are not allowed"),
    "malformed": (scene("<shape type='obj'>"), {}, "scene.xml", "malformed XML: mismatched tag"),
    "not a scene": ('<shape type="obj"/>', {}, "scene.xml", "root element must be <scene>, not <shape>"),
    "namespace": (scene('<path xmlns="urn:x" value="/etc"/>'), {}, "scene.xml", "XML namespaces are not allowed"),
    "latin-1 fragment": (MAIN, valid_files(**{"fragments/materials.xml": MATERIALS.encode() + b"<!-- \xe9 -->"}),
                         "scene.files[fragments/materials.xml]", "must be UTF-8"),
}


@pytest.mark.parametrize("xml, files, field, fragment", list(MALICIOUS.values()), ids=list(MALICIOUS))
def test_malicious_uploads_are_refused(xml, files, field, fragment):
    with pytest.raises(InvalidJob) as caught:
        check_scene_upload(xml, files)
    assert caught.value.field.startswith(field)
    assert fragment in caught.value.message


SMALL_FILES = {"fragments/materials.xml": "<scene/>", "meshes/quad.obj": b"v 0 0 0\n"}  # 16 bytes
LIMITS = UploadLimits(max_files=3, max_file_bytes=64, max_total_bytes=len(MAIN) + 70, max_xml_bytes=len(MAIN))


@pytest.mark.parametrize("xml, extra, field, fragment", [
    (MAIN, {"big.bin": b"x" * 65}, "scene.files[big.bin]", "65 bytes, more than 64, the limit per file"),
    (MAIN, {"huge.bin": b"x" * 1000}, "scene.files[huge.bin]", "more than 64 bytes, the limit per file"),
    (MAIN, {"a": b"", "b": b""}, "scene.files", "4 files uploaded; at most 3"),
    (MAIN, {"c.bin": b"x" * 60}, "scene.files", f"exceed {len(MAIN) + 70} bytes in total"),
    (MAIN + " ", {}, "scene.xml", f"at most {len(MAIN)} are allowed"),
], ids=["file", "file before decoding", "count", "total", "xml"])
def test_limits_are_enforced(xml, extra, field, fragment):
    assert check_scene_upload(MAIN, valid_files(**SMALL_FILES), LIMITS)  # fails only because of `extra`
    files = valid_files(**SMALL_FILES, **extra)
    with pytest.raises(InvalidJob) as caught:
        check_scene_upload(xml, files, LIMITS)
    assert caught.value.field == field
    assert fragment in caught.value.message


def write_tree(root: Path, files: dict[str, str | bytes]) -> None:
    for rel, data in files.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        (root / rel).write_bytes(data.encode() if isinstance(data, str) else data)


def test_pack_scene_round_trips_through_the_check(tmp_path):
    write_tree(tmp_path, {"scene.xml": MAIN, "fragments/materials.xml": MATERIALS, "meshes/quad.obj": OBJ_QUAD,
                          "unused.obj": b"not packed"})
    xml, files = pack_scene(tmp_path / "scene.xml")
    assert xml == MAIN and set(files) == {"fragments/materials.xml", "meshes/quad.obj"}
    assert check_scene_upload(xml, files) == {"fragments/materials.xml": MATERIALS.encode(),
                                              "meshes/quad.obj": OBJ_QUAD}


@pytest.mark.parametrize("tree, error, fragment", [
    ({"fragments/materials.xml": MATERIALS}, FileNotFoundError, "file path 'meshes/quad.obj' does not exist"),
    ({"meshes/quad.obj": OBJ_QUAD}, FileNotFoundError, "include 'fragments/materials.xml' does not exist"),
    ({"meshes/quad.obj": OBJ_QUAD, "fragments/materials.xml": scene(mesh("../outside.obj"))}, ValueError,
     "file path '../outside.obj' must stay inside the scene folder"),
    ({"meshes/quad.obj": OBJ_QUAD, "fragments/materials.xml": scene('<include filename="fragments/materials.xml"/>')},
     ValueError, "include cycle"),
], ids=["missing mesh", "missing include", "leaves folder", "cycle"])
def test_pack_scene_reports_bad_references(tmp_path, tree, error, fragment):
    write_tree(tmp_path / "scene", {"scene.xml": MAIN, **tree})
    (tmp_path / "outside.obj").write_bytes(OBJ_QUAD)
    with pytest.raises(error, match=fragment.replace("(", r"\(")):
        pack_scene(tmp_path / "scene" / "scene.xml")


# ------------------------------------------------------------------ work caps of the expanded scene

DEFAULTS = UploadLimits()


def ply_mesh(vertices: int, faces: int, header_vertices: int | None = None) -> bytes:
    """A binary little-endian PLY of ``vertices`` points and ``faces`` triangles (0, 1, 2)."""
    header = (f"ply\nformat binary_little_endian 1.0\nelement vertex {header_vertices or vertices}\n"
              "property float x\nproperty float y\nproperty float z\n"
              f"element face {faces}\nproperty list uchar int vertex_indices\nend_header\n").encode()
    rows = np.zeros(faces, dtype=[("n", "u1"), ("i", "<i4", 3)])
    rows["n"], rows["i"] = 3, (0, 1, 2)
    return header + np.zeros((vertices, 3), "<f4").tobytes() + rows.tobytes()


def ply_shape(filename: str = "m.ply") -> str:
    return f'<shape type="ply"><string name="filename" value="{filename}"/></shape>'


def refused(xml: str, files: dict[str, str | bytes], limits: UploadLimits = DEFAULTS) -> InvalidJob:
    with pytest.raises(InvalidJob) as caught:
        check_scene_upload(xml, {path: b64(data) for path, data in files.items()}, limits)
    return caught.value


def test_deep_nesting_is_refused_while_parsing():
    """The issue's attack: 20,000 nested twosided BSDFs (580 KB) overflow Mitsuba's recursive parser."""
    nested = '<bsdf type="twosided">' * 20_000 + "</bsdf>" * 20_000
    assert 500_000 < len(scene(nested)) < 4 << 20
    error = refused(scene(nested), {})
    assert (error.field, error.message) == ("scene.xml", "elements are nested deeper than 32 levels (max_xml_depth)")
    error = refused(scene('<include filename="deep.xml"/>'), {"deep.xml": scene(nested)})
    assert error.field == "scene.files[deep.xml]" and "nested deeper than 32 levels" in error.message


def test_depth_counts_through_includes():
    """Each document nests 20 levels; the fragment's content sits 19 levels down in the main one."""
    deep = '<bsdf type="twosided">' * 18
    main = scene(deep + '<include filename="f.xml"/>' + "</bsdf>" * 18)
    fragment = scene(deep + "</bsdf>" * 18)
    assert check_scene_upload(main, {"f.xml": b64(fragment)}, UploadLimits(max_xml_depth=38))
    error = refused(main, {"f.xml": fragment})
    assert error.field == "scene.xml"
    assert error.message == "<bsdf>: nested elements and <ref> chains reach 33 levels in the expanded scene; " \
                            "at most 32 are allowed (max_xml_depth)"


def test_reference_chains_count_as_depth():
    """Mitsuba instantiates referenced objects recursively: 100 BSDFs each wrapping the one
    before by <ref> are as deep as 100 nested ones."""
    chain = '<bsdf type="diffuse" id="b0"/>' + "".join(
        f'<bsdf type="twosided" id="b{i}"><ref id="b{i - 1}"/></bsdf>' for i in range(1, 100))
    error = refused(scene(chain), {})
    assert error.field == "scene.xml" and "<ref> chains reach 33 levels" in error.message
    assert check_scene_upload(scene(chain[:chain.index('id="b10"') - 22]), {}) == {}  # 10 links are fine


def test_reference_cycles_are_refused():
    cycle = '<bsdf type="twosided" id="a"><ref id="b"/></bsdf><bsdf type="twosided" id="b"><ref id="a"/></bsdf>'
    error = refused(scene(cycle), {})
    assert (error.field, error.message) == ("scene.xml", "reference cycle through id 'a'")


def test_a_fragment_counts_every_time_it_is_included():
    """The issue's attack: one fragment included 1,000 times."""
    fragment = scene('<bsdf type="diffuse">' + '<float name="x" value="1"/>' * 148 + "</bsdf>")
    main = scene('<include filename="f.xml"/>' * 1000)
    error = refused(main, {"f.xml": fragment})
    assert error.field == "scene.files[f.xml]"
    assert error.message == "the expanded scene has 151001 XML elements (150000 from this document, included 1000 " \
                            "times); at most 100000 are allowed (max_xml_elements)"
    assert check_scene_upload(scene('<include filename="f.xml"/>' * 600), {"f.xml": b64(fragment)})


def test_expanded_xml_bytes_are_capped():
    fragment = scene(f'<bsdf type="diffuse"><string name="note" value="{"x" * 20_000}"/></bsdf>')
    error = refused(scene('<include filename="f.xml"/>' * 1000), {"f.xml": fragment})
    assert error.field == "scene.files[f.xml]"
    assert f"({len(fragment) * 1000} from this document, included 1000 times); at most {16 << 20} are allowed " \
           "(max_expanded_xml_bytes)" in error.message


def test_one_mesh_referenced_50000_times_is_refused():
    """The issue's attack, through a fragment of 50 shapes included 1,000 times, and directly."""
    files = {"m.ply": ply_mesh(3, 1), "f.xml": scene(ply_shape() * 50)}
    error = refused(scene('<include filename="f.xml"/>' * 1000), files)
    assert error.field == "scene.files[f.xml]"
    assert error.message == "the expanded scene has 50000 <shape> elements (50000 from this document, included " \
                            "1000 times); at most 10000 are allowed (max_shapes)"
    error = refused(scene(ply_shape() * 50_000), files)
    assert (error.field, error.message) == ("scene.xml", "has more than 100000 XML elements (max_xml_elements)")


def test_referenced_bytes_count_per_reference(monkeypatch):
    """A 1.1 MB mesh named by 300 shapes makes Mitsuba read 342 MB; it is checked once."""
    from services.uploads import scene as scene_checks

    checked = []
    real = scene_checks.check_mesh
    monkeypatch.setattr(scene_checks, "check_mesh", lambda *args, **kw: checked.append(args[0]) or real(*args, **kw))
    mesh = ply_mesh(30_000, 60_000)
    error = refused(scene(ply_shape("meshes/m.ply") * 300), {"meshes/m.ply": mesh})
    assert error.field == "scene.files[meshes/m.ply]"
    assert error.message == f"is referenced 300 times ({300 * len(mesh)} bytes of files); the expanded scene " \
                            f"references {300 * len(mesh)} bytes of files in total; at most {256 << 20} are allowed " \
                            "(max_referenced_bytes)"
    assert checked == ["meshes/m.ply"]
    assert check_scene_upload(scene(ply_shape("meshes/m.ply") * 200), {"meshes/m.ply": b64(mesh)})


def test_mesh_work_is_summed_per_reference():
    files = {"m.ply": ply_mesh(4, 2), "f.xml": scene(ply_shape() * 3)}
    limits = UploadLimits(max_scene_faces=10)
    assert check_scene_upload(scene('<include filename="f.xml"/>'), {p: b64(d) for p, d in files.items()}, limits)
    error = refused(scene('<include filename="f.xml"/>' * 2), files, limits)
    assert error.field == "scene.files[m.ply]"
    assert error.message == ("is referenced 6 times (12 mesh faces); the expanded scene references 12 mesh faces in "
                             "total; at most 10 are allowed (max_scene_faces)")


def test_ply_count_overflow_is_refused_through_the_scene():
    """The issue's 49 KB attack: `element vertex 4294967297` in an uploaded m.ply."""
    mesh = ply_mesh(4000, 1, header_vertices=4294967297)
    error = refused(scene(ply_shape("meshes/m.ply")), {"meshes/m.ply": mesh})
    assert (error.field, error.message) == ("scene.files[meshes/m.ply]",
                                            "declares 4294967297 vertices; counts must be below 2^31")


def test_meshes_are_checked_as_the_shape_type_reads_them():
    shape = '<shape type="ply"><string name="filename" value="meshes/quad.obj"/></shape>'
    error = refused(scene(shape), {"meshes/quad.obj": OBJ_QUAD})
    assert (error.field, error.message) == ("scene.files[meshes/quad.obj]",
                                            "is not a PLY file: it must start with a 'ply' line")


def serialized_mesh(shapes: int) -> bytes:
    """Mitsuba's serialized format: per shape uint16 0x041C, uint16 4, a zlib stream (flags, name,
    uint64 counts, float32 positions, uint32 triangles); then the offsets and the shape count."""
    data, offsets = b"", []
    for _ in range(shapes):
        payload = struct.pack("<I", 0x1000) + b"tri\0" + struct.pack("<QQ", 3, 1) + bytes(36) \
            + struct.pack("<3I", 0, 1, 2)
        offsets.append(len(data))
        data += struct.pack("<HH", 0x041C, 4) + zlib.compress(payload)
    return data + struct.pack(f"<{shapes}QI", *offsets, shapes)


@pytest.mark.parametrize("index, fragment", [
    ('<integer name="shape_index" value="2"/>', "shape_index 2 is out of range; 'm.serialized' holds 2 shapes"),
    ('<integer name="shape_index" value="$i"/>', "shape_index must be a literal non-negative integer, not '$i'"),
], ids=["out of range", "substituted"])
def test_serialized_shape_index_is_checked(index, fragment):
    shape = f'<shape type="serialized"><string name="filename" value="m.serialized"/>{index}</shape>'
    files = {"m.serialized": serialized_mesh(2)}
    valid = shape.replace(index, '<integer name="shape_index" value="1"/>')
    assert check_scene_upload(scene(valid), {p: b64(d) for p, d in files.items()})
    error = refused(scene(shape), files)
    assert error.field == "scene.xml" and fragment in error.message


def png(width: int, height: int) -> bytes:
    from PIL import Image

    buffer = io.BytesIO()
    Image.new("L", (width, height)).save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def test_textures_are_capped_from_their_headers():
    """A 3000 x 3000 PNG of ~9 KB as a bitmap texture or environment map."""
    texture = '<texture type="bitmap"><string name="filename" value="t.png"/></texture>'
    envmap = '<emitter type="envmap"><string name="filename" value="t.png"/></emitter>'
    files = {"t.png": png(3000, 3000)}
    for element in (texture, envmap):
        error = refused(scene(element), files, UploadLimits(max_texture_pixels=4 << 20))
        assert error.field == "scene.files[t.png]"
        assert error.message == ("is a 3000 x 3000 PNG image (9000000 pixels); at most 4194304 pixels are allowed "
                                 "(max_texture_pixels)")
    error = refused(scene(texture * 8), files)
    assert error.field == "scene.files[t.png]" and "references 72000000 texture pixels in total; at most " \
                                                   f"{64 << 20} are allowed (max_scene_texture_pixels)" in error.message
    error = refused(scene(texture), {"t.png": b"GIF89a" + bytes(20)})
    assert error.field == "scene.files[t.png]" and "unknown image format" in error.message


def test_valid_scene_with_every_checked_kind_of_file():
    xml = scene('<include filename="f.xml"/>', ply_shape("meshes/m.ply"),
                '<shape type="serialized"><string name="filename" value="meshes/s.serialized"/>'
                '<integer name="shape_index" value="1"/></shape>',
                '<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                '<string name="filename" value="textures/t.png"/></texture></bsdf>')
    files = {"f.xml": scene(mesh("meshes/quad.obj")), "meshes/quad.obj": OBJ_QUAD, "meshes/m.ply": ply_mesh(4, 2),
             "meshes/s.serialized": serialized_mesh(2), "textures/t.png": png(16, 8)}
    assert set(check_scene_upload(xml, {p: b64(d) for p, d in files.items()})) == set(files)


LONG_NAME = "é" * 150 + ".obj"  # 154 characters, 304 bytes in UTF-8


@pytest.mark.parametrize("xml, files, field, fragment", [
    (MAIN, {LONG_NAME: b""}, f"scene.files[{LONG_NAME}]",
     ("the name 'éééééééééééééééééééééééééééééééééééééééé'... (154 characters) has 304 bytes in UTF-8; at most 255 "
      "bytes are allowed per file or folder name")),
    (MAIN, {"meshes/" + LONG_NAME: b""}, f"scene.files[meshes/{LONG_NAME}]", "has 304 bytes in UTF-8"),
    (scene(mesh(LONG_NAME)), {}, "scene.xml", "has 304 bytes in UTF-8; at most 255 bytes"),
    (MAIN, {"a\udc80.obj": b""}, "scene.files[a\udc80.obj]", "is not valid Unicode (it contains a lone surrogate)"),
    (scene('<bsdf type="diffuse" id="\udc80"/>'), {}, "scene.xml", "is not valid Unicode text"),
], ids=["file key", "folder file", "xml reference", "surrogate key", "surrogate xml"])
def test_names_must_fit_the_filesystem(xml, files, field, fragment):
    error = refused(xml, files)
    assert error.field == field and fragment in error.message

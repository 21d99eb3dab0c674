"""Sandboxing of uploaded Mitsuba XML scenes (no Mitsuba needed)."""

from __future__ import annotations

import base64
from pathlib import Path

import pytest

from services.scene.sandbox import (
    MAX_INCLUDE_EXPANSIONS,
    SandboxError,
    UploadLimits,
    check_scene_upload,
    pack_scene,
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
    error = SandboxError("scene.xml", "bad")
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
    with pytest.raises(SandboxError) as caught:
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
    with pytest.raises(SandboxError) as caught:
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

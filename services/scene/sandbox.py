"""Validate an untrusted Mitsuba 3 XML scene and the files uploaded with it.

Threat model: the worker writes the document as ``scene.xml`` and the files into one job folder and
calls ``mitsuba.load_file``. Mitsuba 3.9 looks relative names up through its global file resolver
(the including file's folder, the job folder, then the worker's working directory) and uses
absolute names as they are, so a scene could read any host file. The rules that close the holes:

* ``<include filename>`` and file parameters (``<string name="filename">``, ``<spectrum filename>``)
  must name an uploaded file by a plain relative path; a missing one would fall through to the
  working directory. Included fragments get the same checks and may include others only from the
  top of the folder, where Mitsuba and this check look them up alike.
* ``<path>`` adds host folders to the resolver: refused.
* ``<default>``/``$name`` substitution rewrites attributes after this check: no ``$`` in names,
  types or file names, no ``/`` in a value that uses or defines a substitution.
* ``type`` loads ``plugins/<type>.so`` through the same resolver (uploaded code would run): types are
  plain names, and the top-level ``plugins/`` and ``data/`` (Mitsuba's built-in data) are reserved.
* Attribute values that look like absolute host paths or contain ``../`` are refused anywhere.
* defusedxml without DTDs stops billion laughs and external entities; UTF-8 only and no namespaces
  keep expat (here) and pugixml (Mitsuba) reading the same document; sizes, include depth and
  include expansions are capped.
"""

from __future__ import annotations

import base64
import binascii
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Mapping
from xml.etree.ElementTree import Element, ParseError

import defusedxml
import defusedxml.ElementTree as safe_et

MAIN_XML_NAME = "scene.xml"  # where services.scene.load.write_scene_files writes the document
RESERVED_FOLDERS = ("plugins", "data")  # Mitsuba finds its plugins and data via the file resolver
MAX_INCLUDE_DEPTH = 15  # Mitsuba's ParserConfig.max_include_depth
MAX_INCLUDE_EXPANSIONS = 1024  # fragments Mitsuba would parse, repeats included
MAX_PATH_CHARS = 255

_CONTROL = re.compile(r"[\x00-\x1f\x7f]")
_PLUGIN_TYPE = re.compile(r"[A-Za-z0-9_]+")


class SandboxError(ValueError):
    """An upload that is refused; ``field`` names the offending part of the job JSON."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


@dataclass(frozen=True)
class UploadLimits:
    max_files: int = 256
    max_file_bytes: int = 32 << 20  # one decoded file (mesh, texture)
    max_total_bytes: int = 64 << 20  # all decoded files + xml
    max_xml_bytes: int = 4 << 20


def check_scene_upload(xml: str, files: Mapping[str, str],
                       limits: UploadLimits = UploadLimits()) -> dict[str, bytes]:
    """Validate and decode. Returns {normalized relative path: decoded bytes}.

    Raises SandboxError naming the JSON field: 'scene.xml' for the main document, 'scene.files' for
    the number and total size of the files, f'scene.files[{path}]' (the path as given) for a file
    and for problems inside an included XML fragment.
    """
    size = len(xml.encode("utf-8", "surrogatepass"))
    if size > limits.max_xml_bytes:
        raise SandboxError("scene.xml", f"has {size} bytes; at most {limits.max_xml_bytes} are allowed")
    blobs = _decode_files(files, limits, budget=limits.max_total_bytes - size)
    _check_includes(blobs, _check_document(_parse(xml, "scene.xml"), "scene.xml", blobs))
    return blobs


def scene_references(xml: str) -> tuple[list[str], list[str]]:
    """(include filenames, other file references) found in one XML document, in document order
    (no validation)."""
    return _references(_parse(xml, "scene.xml"))


def pack_scene(xml_path: str | Path) -> tuple[str, dict[str, str]]:
    """Trusted local use (CLI): read an XML file, follow its includes recursively and collect every
    referenced file relative to the XML's folder; return (xml text, {relative path: base64}) ready
    for check_scene_upload. Raise FileNotFoundError/ValueError with a clear message for a missing
    reference or one that leaves the folder."""
    main = Path(xml_path)
    folder = main.parent
    packed: dict[str, str] = {}

    def add(where: Path, what: str, rel: str) -> Path:
        problem = _path_problem(rel, what)
        if problem:
            raise ValueError(f"{where}: {problem}")
        if not (folder / rel).is_file():
            raise FileNotFoundError(f"{where}: {what} {rel!r} does not exist in {folder}")
        packed.setdefault(rel, base64.b64encode((folder / rel).read_bytes()).decode("ascii"))
        return folder / rel

    def visit(where: Path, text: str, chain: tuple[Path, ...]) -> None:
        includes, others = _references(_parse(text, str(where)))
        for name in others:
            add(where, "file path", name)
        for name in includes:
            fragment = add(where, "include", name)
            if fragment in chain:
                raise ValueError(f"{where}: include cycle {' -> '.join(map(str, chain + (fragment,)))}")
            visit(fragment, fragment.read_text(encoding="utf-8"), chain + (fragment,))

    text = main.read_text(encoding="utf-8")
    visit(main, text, (main,))
    return text, packed


def _decode_files(files: Mapping[str, str], limits: UploadLimits, budget: int) -> dict[str, bytes]:
    if len(files) > limits.max_files:
        raise SandboxError("scene.files", f"{len(files)} files uploaded; at most {limits.max_files} are allowed")
    blobs: dict[str, bytes] = {}
    for path, value in files.items():
        field = f"scene.files[{path}]"
        problem = _path_problem(path, "file path") or _reserved_problem(path)
        if problem:
            raise SandboxError(field, problem)
        blobs[path] = _decode_base64(value, field, limits.max_file_bytes)
        budget -= len(blobs[path])
        if budget < 0:
            raise SandboxError("scene.files", f"files and document exceed {limits.max_total_bytes} bytes in total")
    for path in blobs:
        parts = path.split("/")
        for parent in ("/".join(parts[:i]) for i in range(1, len(parts))):
            if parent in blobs:
                raise SandboxError(f"scene.files[{path}]", f"{parent!r} is uploaded as a file, not a folder")
    return blobs


def _decode_base64(value: str, field: str, max_bytes: int) -> bytes:
    if len(value) > 4 * ((max_bytes + 2) // 3):
        raise SandboxError(field, f"decodes to more than {max_bytes} bytes, the limit per file")
    try:
        data = base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise SandboxError(field, f"is not valid base64 (standard alphabet, padded, no whitespace): {exc}") from None
    if len(data) > max_bytes:
        raise SandboxError(field, f"decodes to {len(data)} bytes, more than {max_bytes}, the limit per file")
    return data


def _path_problem(path: str, what: str) -> str | None:
    """Why ``path`` is not a plain relative POSIX path inside the scene folder, or None."""
    parts = path.split("/")
    if not path or len(path) > MAX_PATH_CHARS:
        return f"{what} {path[:MAX_PATH_CHARS]!r} must have 1 to {MAX_PATH_CHARS} characters"
    if "$" in path:
        return f"{what} {path!r}: substitution ($) is not allowed in file names"
    if _CONTROL.search(path):
        return f"{what} {path!r} must not contain control characters"
    if "\\" in path or re.match(r"[A-Za-z]:", path):
        return f"{what} {path!r} must use '/' separators (no backslashes, no drive letters)"
    if path.startswith("/"):
        return f"{what} {path!r} must be relative to the scene (no leading '/')"
    if ".." in parts:
        return f"{what} {path!r} must stay inside the scene folder (no '..')"
    if "" in parts or "." in parts:
        return f"{what} {path!r} must be normalized (no '//', './' or trailing '/')"
    if parts[0].startswith("~"):
        return f"{what} {path!r} must not start with '~'"
    return None


def _reserved_problem(path: str) -> str | None:
    if path == MAIN_XML_NAME:
        return f"{MAIN_XML_NAME!r} is reserved for the main document"
    if "/" in path and path.split("/")[0] in RESERVED_FOLDERS:
        return f"the top-level folders {', '.join(RESERVED_FOLDERS)} are reserved for Mitsuba's plugins and data"
    return None


def _parse(document: str | bytes, field: str) -> Element:
    """Parse text, or bytes that must be UTF-8 (what pugixml assumes without a BOM)."""
    try:
        text = document.decode("utf-8-sig") if isinstance(document, bytes) else document
        return safe_et.fromstring(text, forbid_dtd=True)
    except UnicodeDecodeError:
        raise SandboxError(field, "an XML file must be UTF-8 text") from None
    except defusedxml.DefusedXmlException:
        raise SandboxError(field, "DTD and entities are not allowed") from None
    except ParseError as exc:
        raise SandboxError(field, f"malformed XML: {exc}") from None


def _file_references(element: Element) -> list[tuple[str, str | None]]:
    """``(where, file name)`` for a ``filename`` parameter's value and a ``filename`` attribute."""
    found = []
    if element.get("name") == "filename":
        found.append((f"<{element.tag} name='filename'>", element.get("value")))
    if "filename" in element.attrib:
        found.append((f"<{element.tag} filename=...>", element.get("filename")))
    return found


def _references(root: Element) -> tuple[list[str], list[str]]:
    elements = list(root.iter())
    includes = [element.get("filename", "") for element in elements if element.tag == "include"]
    others = [value for element in elements if element.tag != "include"
              for _, value in _file_references(element) if value is not None]
    return includes, others


def _check_document(root: Element, field: str, blobs: Mapping[str, bytes]) -> list[str]:
    """Check one document (rules 1, 3, 5, 6); return the names it includes, path-checked."""
    if root.tag != "scene":
        raise SandboxError(field, f"the root element must be <scene>, not <{root.tag}>")
    includes = []
    for element in root.iter():
        tag = element.tag
        if tag.startswith("{") or any(name.startswith("{") for name in element.attrib):
            raise SandboxError(field, f"XML namespaces are not allowed (<{tag}>)")
        if tag == "path":
            raise SandboxError(field, "<path> is not allowed: it adds host folders to Mitsuba's file resolver")
        if tag == "include":
            includes.append(_check_name(field, "<include>", "include", element.get("filename")))
        for where, value in _file_references(element) if tag != "include" else ():
            if _check_name(field, where, "file path", value) not in blobs:
                raise SandboxError(field, f"{where}: file {value!r} is not among the uploaded files; "
                                          f"uploaded: {_listing(blobs)}")
        for name, value in element.attrib.items():
            _check_attribute(field, element.tag, name, value)
    return includes


def _check_name(field: str, where: str, what: str, value: str | None) -> str:
    path = value or ""
    problem = _path_problem(path, what)
    if problem:
        raise SandboxError(field, f"{where}: {problem}")
    return path


def _check_attribute(field: str, tag: str, name: str, value: str) -> None:
    where = f"<{tag} {name}={value!r}>"
    if "$" in value and name in ("name", "type"):
        raise SandboxError(field, f"{where}: substitution ($) is not allowed in '{name}' attributes")
    if "/" in value and ("$" in value or tag == "default"):
        raise SandboxError(field, f"{where}: '/' is not allowed in a value that uses or defines a substitution")
    if name == "type" and not _PLUGIN_TYPE.fullmatch(value):
        raise SandboxError(field, f"{where}: a plugin type must be a plain name (letters, digits, '_')")
    if (value.startswith("/") and "/" in value[1:]) or "../" in value:
        raise SandboxError(field, f"{where}: attribute values must not be absolute host paths or contain '../'")


def _check_includes(blobs: Mapping[str, bytes], main_includes: list[str]) -> None:
    """Expand includes as Mitsuba would and check every fragment reached (each parsed once)."""
    fragments: dict[str, list[str]] = {MAIN_XML_NAME: main_includes}
    budget = MAX_INCLUDE_EXPANSIONS

    def walk(document: str, chain: tuple[str, ...]) -> None:
        nonlocal budget
        field = _field(document)
        for name in fragments[document]:
            if "/" in document:
                raise SandboxError(field, f"include {name!r}: only XML files at the top of the scene folder may "
                                          "include others (Mitsuba would look in the fragment's folder first)")
            if name not in blobs:
                raise SandboxError(field, f"include {name!r} is not among the uploaded files; "
                                          f"uploaded: {_listing(blobs)}")
            if name in chain:
                raise SandboxError(field, f"include cycle: {' -> '.join(chain + (name,))}")
            if len(chain) >= MAX_INCLUDE_DEPTH:
                raise SandboxError(field, f"includes are nested deeper than {MAX_INCLUDE_DEPTH} levels")
            budget -= 1
            if budget < 0:
                raise SandboxError(field, f"the scene expands to more than {MAX_INCLUDE_EXPANSIONS} includes")
            if name not in fragments:
                fragments[name] = _check_document(_parse(blobs[name], _field(name)), _field(name), blobs)
            walk(name, chain + (name,))

    walk(MAIN_XML_NAME, (MAIN_XML_NAME,))


def _listing(blobs: Mapping[str, bytes], shown: int = 20) -> str:
    names = sorted(blobs) or ["none"]
    return ", ".join(names[:shown]) + (f", ... ({len(names) - shown} more)" if len(names) > shown else "")


def _field(document: str) -> str:
    return "scene.xml" if document == MAIN_XML_NAME else f"scene.files[{document}]"

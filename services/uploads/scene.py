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
  types or file names, no ``/`` in a value that uses or defines a substitution. The main
  document's own top-level defaults are first substituted into its file names
  (:func:`resolve_scene_defaults`, :mod:`services.uploads.defaults`), and the resolved document
  is what is checked and staged.
* ``type`` loads ``plugins/<type>.so`` through the same resolver (uploaded code would run): types are
  plain names, and the top-level ``plugins/`` and ``data/`` (Mitsuba's built-in data) are reserved.
* Attribute values that look like absolute host paths or contain ``../`` are refused anywhere.
* defusedxml without DTDs stops billion laughs and external entities; UTF-8 only and no namespaces
  keep expat (here) and pugixml (Mitsuba) reading the same document; sizes, include depth and
  include expansions are capped.
* File names are valid Unicode whose UTF-8 form fits the filesystem (255 bytes per component,
  4096 in all): the job folder is written with these names.

Work caps (:class:`UploadLimits`), on the scene as Mitsuba expands it: a fragment counts every time
it is included and a file every time it is referenced, so one fragment included 1,000 times or
one mesh named by 50,000 shapes costs what it costs Mitsuba.

* Mitsuba's parser and its object instantiation recurse, through nested elements and through
  ``<ref>`` chains alike (20,000 nested ``<bsdf>`` overflow its stack). The parse here stops as
  soon as one document nests deeper than ``max_xml_depth`` or has more than ``max_xml_elements``
  elements (a streaming target; ElementTree's C parser itself builds deep trees without
  recursion), and the longest chain of the expanded scene, includes resolved and references
  followed, is computed iteratively and capped by ``max_xml_depth``; a ``<ref>`` cycle is refused.
* Expanded element count, XML bytes and ``<shape>`` count are capped.
* Every file a plugin reads counts its bytes per reference (``max_referenced_bytes``). Meshes read
  by ``ply``/``obj``/``serialized`` shapes pass :func:`services.uploads.meshes.check_mesh` once per
  file, and their vertices and faces are summed per reference; bitmap textures and environment maps
  pass :func:`services.uploads.images.check_image` (pixels per image and summed per reference).
"""

from __future__ import annotations

import logging
import re
from collections import defaultdict
from collections.abc import Iterator, Mapping
from dataclasses import dataclass
from xml.etree.ElementTree import Element, ParseError, TreeBuilder

import defusedxml
import defusedxml.ElementTree as safe_et

from schemas.errors import InvalidJob
from services.uploads.defaults import resolve_file_defaults
from services.uploads.images import check_image
from services.uploads.meshes import MESH_TYPES, MeshSummary, check_mesh
from services.uploads.paths import (
    MAIN_XML_NAME,
    decode_base64,
    path_problem,
    reserved_problem,
)

log = logging.getLogger(__name__)

MAX_INCLUDE_DEPTH = 15  # Mitsuba's ParserConfig.max_include_depth
MAX_INCLUDE_EXPANSIONS = 1024  # fragments Mitsuba would parse, repeats included
_PLUGIN_TYPE = re.compile(r"[A-Za-z0-9_]+")


@dataclass(frozen=True)
class UploadLimits:
    """Caps on one uploaded scene. The XML and work caps apply to the scene as Mitsuba expands
    it: an included fragment counts every time it is included, a file every time it is referenced."""

    max_files: int = 256  # files in the upload
    max_file_bytes: int = 32 << 20  # one decoded file (mesh, texture)
    max_total_bytes: int = 64 << 20  # all decoded files + xml
    max_xml_bytes: int = 4 << 20  # the main document
    max_xml_depth: int = 32  # nesting of the expanded scene, <ref> chains followed (Mitsuba recurses)
    max_xml_elements: int = 100_000  # elements of the expanded scene
    max_expanded_xml_bytes: int = 16 << 20  # XML bytes Mitsuba parses, each inclusion counted
    max_shapes: int = 10_000  # <shape> elements of the expanded scene
    max_referenced_bytes: int = 256 << 20  # bytes of files plugins read, counted per reference
    max_mesh_vertices: int = 10_000_000  # one mesh (one shape of a serialized file)
    max_mesh_faces: int = 20_000_000  # triangles of one mesh
    max_mesh_decompressed_bytes: int = 256 << 20  # inflated bytes of one serialized file
    max_scene_vertices: int = 20_000_000  # mesh vertices summed over every shape reference
    max_scene_faces: int = 40_000_000  # mesh triangles summed over every shape reference
    max_texture_pixels: int = 4096 * 4096  # one bitmap texture or environment map
    max_scene_texture_pixels: int = 64 << 20  # texture pixels summed over every reference


@dataclass
class _Document:
    """One parsed XML document of the scene: the main one or an included fragment."""

    name: str  # MAIN_XML_NAME or the fragment's path
    root: Element
    size: int  # bytes
    elements: int
    includes: list[str]  # in document order, repeats kept

    @property
    def field(self) -> str:
        return _field(self.name)


def resolve_scene_defaults(xml: str, limits: UploadLimits = UploadLimits()) -> str:
    """The main document with its own ``<default>`` values substituted into its file names
    (:mod:`services.uploads.defaults`): what is checked and staged. Call before
    :func:`check_scene_upload`."""
    size = len(xml.encode("utf-8", "surrogatepass"))
    if size > limits.max_xml_bytes:
        raise InvalidJob("scene.xml", f"has {size} bytes; at most {limits.max_xml_bytes} are allowed")
    return resolve_file_defaults(parse_scene_xml(xml, "scene.xml", limits)[0], xml, "scene.xml")


def check_scene_upload(xml: str, files: Mapping[str, str],
                       limits: UploadLimits = UploadLimits()) -> dict[str, bytes]:
    """Validate and decode. Returns {normalized relative path: decoded bytes}.

    Raises InvalidJob naming the JSON field: 'scene.xml' for the main document, 'scene.files' for
    the number and total size of the files, f'scene.files[{path}]' (the path as given) for a file
    and for problems inside an included XML fragment. A work cap of the expanded scene names the
    document (XML caps) or the referenced file (reference caps) that adds the most, and the
    :class:`UploadLimits` field exceeded.
    """
    size = len(xml.encode("utf-8", "surrogatepass"))
    if size > limits.max_xml_bytes:
        raise InvalidJob("scene.xml", f"has {size} bytes; at most {limits.max_xml_bytes} are allowed")
    blobs = _decode_files(files, limits, budget=limits.max_total_bytes - size)
    root, elements = parse_scene_xml(xml, "scene.xml", limits)
    main = _Document(MAIN_XML_NAME, root, size, elements, _check_document(root, "scene.xml", blobs))
    documents = _check_includes(blobs, main, limits)
    _check_expansion(documents, blobs, limits)
    return blobs


def scene_references(xml: str) -> tuple[list[str], list[str]]:
    """(include filenames, other file references) found in one XML document, in document order
    (no validation)."""
    return file_references(parse_scene_xml(xml, "scene.xml")[0])


def _decode_files(files: Mapping[str, str], limits: UploadLimits, budget: int) -> dict[str, bytes]:
    if len(files) > limits.max_files:
        raise InvalidJob("scene.files", f"{len(files)} files uploaded; at most {limits.max_files} are allowed")
    blobs: dict[str, bytes] = {}
    for path, value in files.items():
        field = f"scene.files[{path}]"
        problem = path_problem(path, "file path") or reserved_problem(path)
        if problem:
            raise InvalidJob(field, problem)
        blobs[path] = decode_base64(value, field, limits.max_file_bytes)
        budget -= len(blobs[path])
        if budget < 0:
            raise InvalidJob("scene.files", f"files and document exceed {limits.max_total_bytes} bytes in total")
    for path in blobs:
        parts = path.split("/")
        for parent in ("/".join(parts[:i]) for i in range(1, len(parts))):
            if parent in blobs:
                raise InvalidJob(f"scene.files[{path}]", f"{parent!r} is uploaded as a file, not a folder")
    return blobs


class _CappedTree:
    """ElementTree target that builds the tree but stops the parse as soon as the document nests
    deeper than ``max_depth`` or has more than ``max_elements`` elements."""

    def __init__(self, field: str, max_depth: int, max_elements: int):
        self._builder = TreeBuilder()
        self._field, self._max_depth, self._max_elements = field, max_depth, max_elements
        self.depth = self.elements = 0

    def start(self, tag, attrs):
        self.depth += 1
        self.elements += 1
        if self.depth > self._max_depth:
            raise InvalidJob(self._field, f"elements are nested deeper than {self._max_depth} levels (max_xml_depth)")
        if self.elements > self._max_elements:
            raise InvalidJob(self._field, f"has more than {self._max_elements} XML elements (max_xml_elements)")
        return self._builder.start(tag, attrs)

    def end(self, tag):
        self.depth -= 1
        return self._builder.end(tag)

    def data(self, data):
        self._builder.data(data)

    def close(self):
        return self._builder.close()


def parse_scene_xml(document: str | bytes, field: str, limits: UploadLimits = UploadLimits()) -> tuple[Element, int]:
    """Parse text, or bytes that must be UTF-8 (what pugixml assumes without a BOM); returns the
    root and the number of elements. Depth and element count are capped while parsing."""
    try:
        text = document.decode("utf-8-sig") if isinstance(document, bytes) else document
        text.encode("utf-8")  # lone surrogates (possible in JSON strings) cannot reach expat
        target = _CappedTree(field, limits.max_xml_depth, limits.max_xml_elements)
        parser = safe_et.DefusedXMLParser(target=target, forbid_dtd=True)
        parser.feed(text)
        return parser.close(), target.elements
    except UnicodeDecodeError:
        raise InvalidJob(field, "an XML file must be UTF-8 text") from None
    except UnicodeEncodeError:
        raise InvalidJob(field, "is not valid Unicode text (it contains a lone surrogate)") from None
    except defusedxml.DefusedXmlException:
        raise InvalidJob(field, "DTD and entities are not allowed") from None
    except ParseError as exc:
        raise InvalidJob(field, f"malformed XML: {exc}") from None


def _file_references(element: Element) -> list[tuple[str, str | None]]:
    """``(where, file name)`` for a ``filename`` parameter's value and a ``filename`` attribute."""
    found = []
    if element.get("name") == "filename":
        found.append((f"<{element.tag} name='filename'>", element.get("value")))
    if "filename" in element.attrib:
        found.append((f"<{element.tag} filename=...>", element.get("filename")))
    return found


def file_references(root: Element) -> tuple[list[str], list[str]]:
    elements = list(root.iter())
    includes = [element.get("filename", "") for element in elements if element.tag == "include"]
    others = [value for element in elements if element.tag != "include"
              for _, value in _file_references(element) if value is not None]
    return includes, others


def _check_document(root: Element, field: str, blobs: Mapping[str, bytes]) -> list[str]:
    """Check one document (rules 1, 3, 5, 6); return the names it includes, path-checked."""
    if root.tag != "scene":
        raise InvalidJob(field, f"the root element must be <scene>, not <{root.tag}>")
    includes = []
    for element in root.iter():
        tag = element.tag
        if tag.startswith("{") or any(name.startswith("{") for name in element.attrib):
            raise InvalidJob(field, f"XML namespaces are not allowed (<{tag}>)")
        if tag == "path":
            raise InvalidJob(field, "<path> is not allowed: it adds host folders to Mitsuba's file resolver")
        if tag == "include":
            includes.append(_check_name(field, "<include>", "include", element.get("filename")))
        for where, value in _file_references(element) if tag != "include" else ():
            if _check_name(field, where, "file path", value) not in blobs:
                raise InvalidJob(field, f"{where}: file {value!r} is not among the uploaded files; "
                                          f"uploaded: {_listing(blobs)}")
        for name, value in element.attrib.items():
            _check_attribute(field, element.tag, name, value)
    return includes


def _check_name(field: str, where: str, what: str, value: str | None) -> str:
    path = value or ""
    problem = path_problem(path, what)
    if problem:
        raise InvalidJob(field, f"{where}: {problem}")
    return path


def _check_attribute(field: str, tag: str, name: str, value: str) -> None:
    where = f"<{tag} {name}={value!r}>"
    if "$" in value and name in ("name", "type"):
        raise InvalidJob(field, f"{where}: substitution ($) is not allowed in '{name}' attributes")
    if "/" in value and ("$" in value or tag == "default"):
        raise InvalidJob(field, f"{where}: '/' is not allowed in a value that uses or defines a substitution")
    if name == "type" and not _PLUGIN_TYPE.fullmatch(value):
        raise InvalidJob(field, f"{where}: a plugin type must be a plain name (letters, digits, '_')")
    if (value.startswith("/") and "/" in value[1:]) or "../" in value:
        raise InvalidJob(field, f"{where}: attribute values must not be absolute host paths or contain '../'")


def _check_includes(blobs: Mapping[str, bytes], main: _Document, limits: UploadLimits) -> dict[str, _Document]:
    """Expand includes as Mitsuba would (every path through the include graph, iteratively) and
    check every fragment reached, each parsed once. Returns {name: document}, main included."""
    documents = {MAIN_XML_NAME: main}
    budget = MAX_INCLUDE_EXPANSIONS
    stack: list[tuple[str, tuple[str, ...], Iterator[str]]] = [(MAIN_XML_NAME, (MAIN_XML_NAME,), iter(main.includes))]
    while stack:
        document, chain, pending = stack[-1]
        name = next(pending, None)
        if name is None:
            stack.pop()
            continue
        field = _field(document)
        if "/" in document:
            raise InvalidJob(field, f"include {name!r}: only XML files at the top of the scene folder may "
                                      "include others (Mitsuba would look in the fragment's folder first)")
        if name not in blobs:
            raise InvalidJob(field, f"include {name!r} is not among the uploaded files; "
                                      f"uploaded: {_listing(blobs)}")
        if name in chain:
            raise InvalidJob(field, f"include cycle: {' -> '.join(chain + (name,))}")
        if len(chain) >= MAX_INCLUDE_DEPTH:
            raise InvalidJob(field, f"includes are nested deeper than {MAX_INCLUDE_DEPTH} levels")
        budget -= 1
        if budget < 0:
            raise InvalidJob(field, f"the scene expands to more than {MAX_INCLUDE_EXPANSIONS} includes")
        if name not in documents:
            root, elements = parse_scene_xml(blobs[name], _field(name), limits)
            documents[name] = _Document(name, root, len(blobs[name]), elements,
                                        _check_document(root, _field(name), blobs))
        stack.append((name, chain + (name,), iter(documents[name].includes)))
    return documents


def _check_expansion(documents: dict[str, _Document], blobs: Mapping[str, bytes], limits: UploadLimits) -> None:
    """The work caps of the expanded scene (see the module docstring), cheapest first."""
    times = _inclusions(documents)
    shapes = {d.name: sum(1 for e in d.root.iter("shape")) for d in documents.values()}
    _cap_total(documents, times, shapes, limits.max_shapes, "max_shapes", "<shape> elements")
    _cap_total(documents, times, {d.name: d.elements for d in documents.values()}, limits.max_xml_elements,
               "max_xml_elements", "XML elements")
    _cap_total(documents, times, {d.name: d.size for d in documents.values()}, limits.max_expanded_xml_bytes,
               "max_expanded_xml_bytes", "bytes of XML")
    _check_depth(documents, limits.max_xml_depth)
    _check_references(documents, times, blobs, limits)


def _inclusions(documents: dict[str, _Document]) -> dict[str, int]:
    """How many times each document appears in the expanded scene (the include graph is acyclic)."""
    order, seen = [], {MAIN_XML_NAME}
    stack = [(MAIN_XML_NAME, iter(dict.fromkeys(documents[MAIN_XML_NAME].includes)))]
    while stack:  # iterative depth-first post-order
        name, pending = stack[-1]
        child = next(pending, None)
        if child is None:
            order.append(stack.pop()[0])
        elif child not in seen:
            seen.add(child)
            stack.append((child, iter(dict.fromkeys(documents[child].includes))))
    times = dict.fromkeys(documents, 0)
    times[MAIN_XML_NAME] = 1
    for name in reversed(order):  # parents before children
        for child in documents[name].includes:
            times[child] += times[name]
    return times


def _cap_total(documents: dict[str, _Document], times: dict[str, int], amounts: dict[str, int], cap: int,
               limit: str, what: str) -> None:
    """Refuse when sum(times x amount) exceeds ``cap``, naming the document that adds the most."""
    parts = {name: times[name] * amount for name, amount in amounts.items()}
    total = sum(parts.values())
    if total > cap:
        name = max(parts, key=parts.__getitem__)
        included = f", included {times[name]} times" if times[name] > 1 else ""
        raise InvalidJob(_field(name), f"the expanded scene has {total} {what} ({parts[name]} from this "
                                       f"document{included}); at most {cap} are allowed ({limit})")


def _check_depth(documents: dict[str, _Document], max_depth: int) -> None:
    """Longest chain of the expanded scene: element nesting, ``<include>`` replaced by the
    fragment's content, ``<ref id>`` followed to the element with that id. Iterative post-order
    over the elements (a fragment's elements are visited once however often it is included)."""
    owner = {}
    targets: dict[str, list[Element]] = defaultdict(list)
    for document in documents.values():
        for element in document.root.iter():
            owner[element] = document
            if element.tag != "ref" and element.get("id") is not None:
                targets[element.get("id", "")].append(element)

    def children(element: Element) -> list[Element]:
        if element.tag == "include":
            return list(documents[element.get("filename", "")].root)
        if element.tag == "ref":
            return targets.get(element.get("id", ""), [])
        return list(element)

    height: dict[Element, int] = {}
    root = documents[MAIN_XML_NAME].root
    stack = [(root, iter(children(root)), 0)]
    on_path = {root}
    while stack:
        element, pending, deepest = stack[-1]
        child = next(pending, None)
        if child is not None:
            if child in on_path:
                raise InvalidJob(owner[child].field, f"reference cycle through id {child.get('id')!r}")
            if child in height:
                stack[-1] = (element, pending, max(deepest, height[child]))
            else:
                on_path.add(child)
                stack.append((child, iter(children(child)), 0))
            continue
        stack.pop()
        on_path.discard(element)
        height[element] = deepest + (element.tag != "include")  # an include adds no level
        if height[element] > max_depth:
            raise InvalidJob(owner[element].field,
                             f"<{element.tag}>: nested elements and <ref> chains reach {height[element]} levels in "
                             f"the expanded scene; at most {max_depth} are allowed (max_xml_depth)")
        if stack:
            parent, rest, best = stack[-1]
            stack[-1] = (parent, rest, max(best, height[element]))


def _check_references(documents: dict[str, _Document], times: dict[str, int], blobs: Mapping[str, bytes],
                      limits: UploadLimits) -> None:
    """Check meshes and textures once per file; sum what each reference makes Mitsuba read and
    build, and cap the sums."""
    meshes: dict[tuple[str, str], MeshSummary] = {}
    textures: dict[str, int] = {}
    referenced: dict[str, int] = defaultdict(int)  # path -> bytes over every reference
    counts: dict[str, int] = defaultdict(int)  # path -> references
    vertices: dict[str, int] = defaultdict(int)
    faces: dict[str, int] = defaultdict(int)
    pixels: dict[str, int] = defaultdict(int)
    for document in documents.values():
        n = times[document.name]
        parents = {child: parent for parent in document.root.iter() for child in parent}
        for element in document.root.iter():
            if element.tag == "include":
                continue
            for _, path in _file_references(element):
                plugin = parents.get(element) if element.get("name") == "filename" else element
                if path is None or plugin is None:
                    continue
                kind, tag = plugin.get("type", ""), plugin.tag
                cost = len(blobs[path])
                if tag == "shape" and kind in MESH_TYPES:
                    if (path, kind) not in meshes:
                        meshes[(path, kind)] = check_mesh(path, blobs[path], limits, kind=kind)  # type: ignore[arg-type]
                    summary = meshes[(path, kind)].shape(_shape_index(document, plugin, path, meshes[(path, kind)]))
                    cost = summary.bytes
                    vertices[path] += n * summary.vertices
                    faces[path] += n * summary.faces
                elif (tag, kind) in (("texture", "bitmap"), ("emitter", "envmap")):
                    if path not in textures:
                        textures[path] = check_image(f"scene.files[{path}]", blobs[path], limits.max_texture_pixels,
                                                     "max_texture_pixels").pixels
                    pixels[path] += n * textures[path]
                referenced[path] += n * cost
                counts[path] += n
    _cap_files(referenced, counts, limits.max_referenced_bytes, "max_referenced_bytes", "bytes of files")
    _cap_files(vertices, counts, limits.max_scene_vertices, "max_scene_vertices", "mesh vertices")
    _cap_files(faces, counts, limits.max_scene_faces, "max_scene_faces", "mesh faces")
    _cap_files(pixels, counts, limits.max_scene_texture_pixels, "max_scene_texture_pixels", "texture pixels")
    log.debug("scene references %d bytes of files, %d vertices, %d faces, %d texture pixels",
              sum(referenced.values()), sum(vertices.values()), sum(faces.values()), sum(pixels.values()))


def _shape_index(document: _Document, shape: Element, path: str, summary: MeshSummary) -> int:
    """The literal ``shape_index`` of a serialized shape (default 0), within the file's shapes."""
    values = [child.get("value", "") for child in shape if child.get("name") == "shape_index"]
    if not summary.shapes:
        return 0
    value = values[-1] if values else "0"
    if not re.fullmatch(r"[0-9]{1,9}", value):
        raise InvalidJob(document.field, f"<shape type='serialized'> of {path!r}: shape_index must be a literal "
                                         f"non-negative integer, not {value[:20]!r}")
    if int(value) >= len(summary.shapes):
        raise InvalidJob(document.field, f"<shape type='serialized'>: shape_index {value} is out of range; "
                                         f"{path!r} holds {len(summary.shapes)} shapes")
    return int(value)


def _cap_files(amounts: dict[str, int], counts: dict[str, int], cap: int, limit: str, what: str) -> None:
    """Refuse when the amounts summed over every reference exceed ``cap``, naming the file that
    adds the most."""
    total = sum(amounts.values())
    if total > cap:
        path = max(amounts, key=amounts.__getitem__)
        raise InvalidJob(f"scene.files[{path}]", f"is referenced {counts[path]} times ({amounts[path]} {what}); the "
                                                 f"expanded scene references {total} {what} in total; at most {cap} "
                                                 f"are allowed ({limit})")


def _listing(blobs: Mapping[str, bytes], shown: int = 20) -> str:
    names = sorted(blobs) or ["none"]
    return ", ".join(names[:shown]) + (f", ... ({len(names) - shown} more)" if len(names) > shown else "")


def _field(document: str) -> str:
    return "scene.xml" if document == MAIN_XML_NAME else f"scene.files[{document}]"

"""A local scene folder packed for upload (trusted local use: the CLI and ``ndrf run``)."""

from __future__ import annotations

import base64
from collections.abc import Iterator
from pathlib import Path

from services.uploads.defaults import resolve_file_defaults
from services.uploads.paths import path_problem
from services.uploads.scene import file_references, parse_scene_xml


def pack_scene(xml_path: str | Path) -> tuple[str, dict[str, str]]:
    """Trusted local use (CLI): read an XML file, follow its includes recursively and collect every
    referenced file relative to the XML's folder; return (xml text, {relative path: base64}) ready
    for check_scene_upload. Raise FileNotFoundError/ValueError with a clear message for a missing
    reference or one that leaves the folder."""
    main = Path(xml_path)
    folder = main.parent
    packed: dict[str, str] = {}

    def add(where: Path, what: str, rel: str) -> Path:
        problem = path_problem(rel, what)
        if problem:
            raise ValueError(f"{where}: {problem}")
        if not (folder / rel).is_file():
            raise FileNotFoundError(f"{where}: {what} {rel!r} does not exist in {folder}")
        packed.setdefault(rel, base64.b64encode((folder / rel).read_bytes()).decode("ascii"))
        return folder / rel

    def visit(where: Path, text: str) -> Iterator[str]:
        root = parse_scene_xml(text, str(where))[0]
        if where == main:   # the scene's own defaults in its file names, as the service resolves them
            root = parse_scene_xml(resolve_file_defaults(root, text, str(where)), str(where))[0]
        includes, others = file_references(root)
        for name in others:
            add(where, "file path", name)
        return iter(includes)

    text = main.read_text(encoding="utf-8")
    # depth first, in document order, without recursion
    stack: list[tuple[Path, tuple[Path, ...], Iterator[str]]] = [(main, (main,), visit(main, text))]
    while stack:
        where, chain, includes = stack[-1]
        name = next(includes, None)
        if name is None:
            stack.pop()
            continue
        fragment = add(where, "include", name)
        if fragment in chain:
            raise ValueError(f"{where}: include cycle {' -> '.join(map(str, chain + (fragment,)))}")
        stack.append((fragment, chain + (fragment,), visit(fragment, fragment.read_text(encoding="utf-8"))))
    return text, packed

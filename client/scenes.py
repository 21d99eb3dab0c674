"""Pack a local scene (``{"path": "scene.xml"}``) into an upload (``{"xml": ..., "files": {...}}``).

The service refuses host paths; ``ndrf submit`` and ``ndrf experiment`` send the XML and every
file it names instead: ``<include filename=...>`` (read recursively) and every
``<string name="filename" value=...>`` (meshes, textures), by path relative to the main XML's
folder, and a shape job's target mesh files (``targets.synthetic.meshes.<shape id>.file``, relative
to the same folder). The server checks the upload as any other (no absolute paths, no ``..``, sizes).
"""

from __future__ import annotations

import base64
import copy
import xml.etree.ElementTree as ET
from pathlib import Path


class SceneError(ValueError):
    """A local scene that cannot be packed (a file it names is missing, or outside its folder)."""


def _referenced(document: Path) -> list[str]:
    try:
        root = ET.parse(document).getroot()
    except (ET.ParseError, OSError) as exc:
        raise SceneError(f"{document}: {exc}") from None
    names = []
    for element in root.iter():
        if element.tag == "include" and element.get("filename"):
            names.append(element.get("filename", ""))
        elif element.tag == "string" and element.get("name") == "filename" and element.get("value"):
            names.append(element.get("value", ""))
    return names


def pack_files(main: Path) -> tuple[str, dict[str, str]]:
    """The main XML's text and every file it (and its includes) names, base64, by relative path."""
    folder = main.parent.resolve()
    files: dict[str, str] = {}
    pending = [main.resolve()]
    seen: set[Path] = set()
    while pending:
        document = pending.pop()
        if document in seen:
            continue
        seen.add(document)
        for name in _referenced(document):
            if "$" in name:
                raise SceneError(f"{document.name}: {name!r} uses a $variable; write the file name out")
            path = _add(files, folder, name, document.name)
            if path.suffix.lower() == ".xml" and path not in seen:
                pending.append(path)
    return main.read_text(encoding="utf-8"), files


def _add(files: dict[str, str], folder: Path, name: str, where: str) -> Path:
    """Add the file ``name`` (relative to ``folder``) to ``files`` by its relative path, base64."""
    path = (folder / name).resolve()
    if folder not in path.parents:
        raise SceneError(f"{where}: {name!r} is outside the scene's folder {folder}")
    if not path.is_file():
        raise SceneError(f"{where}: {name!r} does not exist ({path})")
    rel = path.relative_to(folder).as_posix()
    if rel not in files:
        files[rel] = base64.b64encode(path.read_bytes()).decode()
    return path


def _pack_targets(job: dict, folder: Path, files: dict[str, str]) -> None:
    """Add the job's target mesh files (``targets.synthetic.meshes.<shape id>.file``, relative to
    the scene's ``folder``) to ``files``, and name each in ``job`` by its path among them."""
    targets = job.get("targets")
    synthetic = targets.get("synthetic") if isinstance(targets, dict) else None
    meshes = synthetic.get("meshes") if isinstance(synthetic, dict) else None
    for shape, mesh in (meshes or {}).items() if isinstance(meshes, dict) else ():
        if isinstance(mesh, dict) and isinstance(mesh.get("file"), str):
            path = _add(files, folder, mesh["file"], f"targets.synthetic.meshes.{shape}.file")
            mesh["file"] = path.relative_to(folder).as_posix()


def pack_scene(job: dict, base_dir: str | Path) -> dict:
    """``job`` with a ``{"path": ...}`` scene (relative to ``base_dir``) replaced by its upload;
    other jobs are returned unchanged. Works on a job file and on an experiment's ``base``."""
    if "base" in job and isinstance(job["base"], dict):
        packed = copy.deepcopy(job)
        packed["base"] = pack_scene(job["base"], base_dir)
        return packed
    scene = job.get("scene")
    if not isinstance(scene, dict) or "path" not in scene:
        return job
    main = Path(scene["path"])
    main = main if main.is_absolute() else Path(base_dir) / main
    xml, files = pack_files(main)
    packed = copy.deepcopy(job)
    _pack_targets(packed, main.parent.resolve(), files)
    packed["scene"] = {"xml": xml, "files": files}
    return packed

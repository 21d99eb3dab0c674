"""Staging of an uploaded scene: check it (:mod:`services.uploads.scene`), then write the XML
and its files into an emptied folder, where a sandboxed child loads it.

The folder is emptied first so that nothing left there can shadow an upload, and created even
when the scene has no files (a self-contained XML is the simplest upload there is). A job's scene
is staged with :func:`stage_job`, which also checks the job's target mesh files
(:mod:`services.uploads.target_meshes`): they are staged with the other files, and read too.
"""

from __future__ import annotations

import shutil
from collections.abc import Mapping
from pathlib import Path

from schemas.errors import InvalidJob
from schemas.job import BuiltinScene, JobSpec, PathScene, SceneSpec, XmlScene
from services.uploads.scene import MAIN_XML_NAME, UploadLimits, check_scene_upload, resolve_scene_defaults
from services.uploads.target_meshes import check_target_files, target_files


def write_scene_files(folder: Path, xml: str, files: dict[str, bytes]) -> Path:
    """Write checked files under an emptied ``folder``; returns the main document's path. Paths
    that would leave the folder are refused once more, as a last line of defence."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)
    root = folder.resolve()
    for rel, data in files.items():
        target = (root / rel).resolve()
        if root not in target.parents:
            raise ValueError(f"scene file path {rel!r} leaves the scene folder")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    main = root / MAIN_XML_NAME
    main.write_text(xml, encoding="utf-8")
    return main


def stage_job(spec: JobSpec, folder: Path, limits: UploadLimits, base_dir: Path | None = None) -> Path | None:
    """:func:`stage_scene` of a job's scene, its target mesh files checked with it."""
    return stage_scene(spec.scene, folder, limits, base_dir, target_files(spec))


def stage_scene(scene: SceneSpec, folder: Path, limits: UploadLimits, base_dir: Path | None = None,
                targets: Mapping[str, str] | None = None) -> Path | None:
    """The file a job's scene loads from: ``None`` for a built-in, the staged ``scene.xml`` of an
    upload (checked against ``limits``; raises :class:`schemas.errors.InvalidJob`), or the local
    file of a :class:`PathScene` resolved against ``base_dir`` (trusted callers only: the service
    refuses host paths before this). ``targets``: the job's target mesh files, ``{field: path}``
    (:func:`~services.uploads.target_meshes.check_target_files`), whose vertices and faces count
    against the scene's caps."""
    cost = check_target_files(targets or {}, scene, limits)
    if isinstance(scene, BuiltinScene):
        return None
    if isinstance(scene, XmlScene):
        xml = resolve_scene_defaults(scene.xml, limits)   # checked and staged as resolved
        try:
            files = check_scene_upload(xml, scene.files, cost.within(limits))
        except InvalidJob as exc:
            if cost.vertices and any(cap in exc.message for cap in ("max_scene_vertices", "max_scene_faces")):
                raise InvalidJob(exc.field, f"{exc.message}, once the target meshes' {cost.vertices} vertices and "
                                            f"{cost.faces} faces are counted") from None
            raise
        return write_scene_files(folder, xml, files)
    if isinstance(scene, PathScene):
        path = Path(scene.path)
        return path if path.is_absolute() or base_dir is None else base_dir / path
    raise TypeError(f"unsupported scene source {type(scene).__name__}")

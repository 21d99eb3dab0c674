"""The target surface of a shape job's synthetic target (``targets.synthetic.meshes``, #34).

A shape's target is a :class:`~.shape.Surface` of any topology, then deformed about the centre of
its own bounding box (:func:`~.shaped.deform`):

* by default, the shape's own mesh: the same vertices and triangles, so the target also has
  differential coordinates, and it is rendered by assigning them;
* ``builtin: rounded-box``: :func:`~.shaped.rounded_box` (866 vertices on a cube's grid), centred
  on the centre of the shape's bounding box, its corners at the shape's radius;
* ``file``: a PLY or OBJ file beside the scene's XML (the staged upload's folder, or a local XML's
  folder), read by Mitsuba, its vertices in world space as they are. The host has checked an
  uploaded one (``services.uploads``) before a sandboxed child reads it here.

The last two have another topology: no differential coordinates, and the target images are
rendered with the mesh's topology swapped to them (:meth:`.shape.MeshReports.showing_targets`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import mitsuba as mi
import numpy as np

from schemas.errors import InvalidJob
from schemas.job import TargetMesh
from services.solver.scene.shape import ShapeMesh, Surface
from services.solver.scene.shaped import deform, rounded_box

log = logging.getLogger(__name__)

#: The mesh files a target may be, by extension: Mitsuba's shape type that reads them.
TARGET_FILE_TYPES = {".ply": "ply", ".obj": "obj"}


def own_topology(target: TargetMesh | None) -> bool:
    """Whether the target is the shape's own mesh (deformed): neither ``file`` nor ``builtin``."""
    return target is None or (target.file is None and target.builtin is None)


def target_surface(mesh: ShapeMesh, target: TargetMesh | None, folder: Path | None, field: str) -> Surface:
    """The target surface of ``mesh``: ``target``'s mesh (module docstring) deformed by its
    ``scale`` and ``bump``. ``folder`` is the scene XML's folder (None for a built-in scene);
    ``field`` the job's path of ``target`` (``targets.synthetic.meshes.<shape id>``), which an
    :class:`InvalidJob` names."""
    if target is None:
        return Surface(mesh.v0, mesh.faces)
    if target.file is not None:
        base = read_surface(folder, target.file, f"{field}.file")
    elif target.builtin == "rounded-box":
        vertices, faces = rounded_box()
        base = Surface(vertices * mesh.radius + mesh.centre, faces)
    else:
        base = Surface(mesh.v0, mesh.faces)
    moved = deform(base.vertices, target.scale, target.bump, target.bump_direction, target.bump_width)
    return Surface(moved, base.faces)


def read_surface(folder: Path | None, name: str, field: str) -> Surface:
    """The surface of the PLY or OBJ file ``name``, relative to ``folder``, as Mitsuba loads it.
    Raises :class:`InvalidJob` on ``field`` for a built-in scene (no folder), a path that leaves
    the folder, a missing file, another format, or a file Mitsuba cannot read."""
    if folder is None:
        raise InvalidJob(field, "a built-in scene has no files: give the target mesh with an XML scene (its files, "
                                "or beside a local XML file), or use builtin")
    root = folder.resolve()
    path = (root / name).resolve()
    if root not in path.parents:
        raise InvalidJob(field, f"{name!r} leaves the scene's folder")
    kind = TARGET_FILE_TYPES.get(path.suffix.lower())
    if kind is None:
        raise InvalidJob(field, f"{name!r} is not a mesh file of a known kind: expected "
                                f"{' or '.join(TARGET_FILE_TYPES)}")
    if not path.is_file():
        raise InvalidJob(field, f"{name!r} does not exist beside the scene")
    try:
        params = mi.traverse(mi.load_dict({"type": kind, "filename": str(path)}))
        surface = Surface.of(np.asarray(params["vertex_positions"], np.float64),
                             np.asarray(params["faces"], np.int64))
    except (RuntimeError, ValueError) as exc:
        raise InvalidJob(field, f"{name!r} could not be read as a {kind} mesh: {exc}") from None
    log.info("target mesh %s: %d vertices, %d triangles", name, len(surface.vertices), len(surface.faces))
    return surface

"""Check a shape job's target mesh files (``targets.synthetic.meshes.<shape id>.file``, #34) before
a sandboxed child reads them.

A target file is not named by the scene's XML, so :func:`services.uploads.scene.check_scene_upload`
does not see it; it is staged with the scene's other files all the same, and the solver reads it
with Mitsuba's ``ply`` or ``obj`` reader. So it passes the same checks as a mesh the XML names:

* it is among the uploaded scene's ``files`` (a built-in scene has none);
* it is a PLY or OBJ file (:func:`services.uploads.meshes.mesh_kind`) and passes
  :func:`services.uploads.meshes.check_mesh` with the service's mesh caps;
* its vertices and faces count against the scene's caps (``max_scene_vertices``,
  ``max_scene_faces``) together with those of the meshes the XML references.

Each refusal is an :class:`InvalidJob` naming ``targets.synthetic.meshes.<shape id>.file``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, replace

from schemas.errors import InvalidJob
from schemas.job import BuiltinScene, JobSpec, PathScene, SceneSpec, SyntheticTargets
from services.uploads.meshes import check_mesh, mesh_kind
from services.uploads.paths import decode_base64, path_problem
from services.uploads.scene import UploadLimits

#: The mesh kinds a target file may be (Mitsuba's ``ply`` and ``obj`` readers).
TARGET_KINDS = ("ply", "obj")


def target_files(spec: JobSpec) -> dict[str, str]:
    """``{field: path}`` of the job's target mesh files, ``field`` being
    ``targets.synthetic.meshes.<shape id>.file``; empty for a job without one."""
    if not isinstance(spec.targets, SyntheticTargets):
        return {}
    return {f"targets.synthetic.meshes.{shape}.file": mesh.file
            for shape, mesh in spec.targets.synthetic.meshes.items() if mesh.file is not None}


@dataclass(frozen=True)
class TargetCost:
    """What the target files make the solver read: ``vertices`` and ``faces`` summed over them."""

    vertices: int = 0
    faces: int = 0

    def within(self, limits: UploadLimits) -> UploadLimits:
        """``limits`` with the scene caps lowered by this cost: what the XML's meshes may add."""
        return replace(limits, max_scene_vertices=limits.max_scene_vertices - self.vertices,
                       max_scene_faces=limits.max_scene_faces - self.faces)


def check_target_files(targets: Mapping[str, str], scene: SceneSpec, limits: UploadLimits) -> TargetCost:
    """Check the target files ``targets`` (``{field: path}``, :func:`target_files`) of a job whose
    scene is ``scene`` (module docstring); returns their cost. A local :class:`PathScene` (trusted,
    the CLI's ``ndrf run``) is not checked here: the solver refuses a path that leaves its folder."""
    if not targets or isinstance(scene, PathScene):
        return TargetCost()
    if isinstance(scene, BuiltinScene):
        field = next(iter(targets))
        raise InvalidJob(field, f"a built-in scene ({scene.builtin}) has no files: upload the target mesh with an "
                                f"XML scene's files, or use builtin")
    vertices = faces = 0
    for field, path in targets.items():
        problem = path_problem(path, "the target mesh")
        if problem:
            raise InvalidJob(field, problem)
        if path not in scene.files:
            raise InvalidJob(field, f"{path!r} is not among the scene's files; uploaded: "
                                    f"{', '.join(sorted(scene.files)[:20]) or 'none'}")
        kind = mesh_kind(path)
        if kind not in TARGET_KINDS:
            raise InvalidJob(field, f"{path!r} is not a mesh file of a kind a target may be: expected a name ending "
                                    f"in {' or '.join('.' + k for k in TARGET_KINDS)}")
        data = decode_base64(scene.files[path], f"scene.files[{path}]", limits.max_file_bytes)
        try:
            summary = check_mesh(path, data, limits, kind=kind)   # type: ignore[arg-type]
        except InvalidJob as exc:
            raise InvalidJob(field, f"{path!r}: {exc.message}") from None
        vertices, faces = vertices + summary.vertices, faces + summary.faces
    cost = TargetCost(vertices, faces)
    for what, amount, cap, name in (("vertices", vertices, limits.max_scene_vertices, "max_scene_vertices"),
                                    ("faces", faces, limits.max_scene_faces, "max_scene_faces")):
        if amount > cap:
            raise InvalidJob(next(iter(targets)), f"the target meshes have {amount} {what}; the scene may have at "
                                                  f"most {cap} ({name})")
    return cost

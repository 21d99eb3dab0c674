"""What every mesh check shares (:mod:`services.uploads.meshes`): the caps, the summary of a
checked file, and the refusal naming the file."""

from __future__ import annotations

from dataclasses import dataclass

from schemas.errors import InvalidJob

MAX_COUNT = 2**31 - 1  # every declared count must be below 2^31
MAX_MESH_COUNT = (2**32 - 1) // 3  # Mitsuba sizes buffers as uint32(count) * 3
MESH_TYPES = ("ply", "obj", "serialized")  # Mitsuba shape types that read a mesh file

CHUNK = 1 << 20  # bytes inflated or parsed at a time

@dataclass(frozen=True)
class MeshLimits:
    """The caps this module applies; :class:`services.uploads.scene.UploadLimits` has the same
    fields and can be passed instead."""

    max_mesh_vertices: int = 10_000_000
    max_mesh_faces: int = 20_000_000
    max_mesh_decompressed_bytes: int = 256 << 20


@dataclass(frozen=True)
class MeshSummary:
    """What loading the file costs: ``vertices`` and ``faces`` (triangles) Mitsuba will build,
    ``bytes`` of the file it reads. For ``serialized``, ``shapes`` has one summary per sub-shape
    (``bytes`` = its compressed stream), since a shape loads one of them (``shape_index``)."""

    format: str
    vertices: int
    faces: int
    bytes: int
    shapes: tuple[MeshSummary, ...] = ()

    def shape(self, index: int) -> MeshSummary:
        """The summary of what ``shape_index=index`` loads (the whole file for PLY/OBJ)."""
        if not self.shapes:
            return self
        return self.shapes[index]


def refuse(path: str, message: str) -> InvalidJob:
    return InvalidJob(f"scene.files[{path}]", message)


def check_count(path: str, what: str, count: int, cap: int, cap_name: str, verb: str = "declares") -> None:
    if count > MAX_COUNT:
        raise refuse(path, f"{verb} {count} {what}; counts must be below 2^31")
    cap = min(cap, MAX_MESH_COUNT)
    if count > cap:
        raise refuse(path, f"{verb} {count} {what}; at most {cap} are allowed per mesh ({cap_name})")

"""Shape parameters: a mesh's vertices, optimized in Mitsuba's ``LargeSteps`` parameterization.

A job names a mesh's vertices by its ``mi.traverse`` key, ``<shape id>.vertex_positions`` (world
space, ``N`` vertices). They are not stepped directly: following Nicolet et al. 2021 ("Large
Steps in Inverse Rendering of Geometry") and Mitsuba's shape-optimization tutorial, the optimized
scalars are the *differential coordinates*::

    u = (I + λ L) v          v: (N', 3) the mesh's distinct vertices, L: its combinatorial Laplacian
    v = (I + λ L)^-1 u       (the sparse Cholesky solve, ``mi.ad.LargeSteps`` over ``cholespy``)

so a gradient ``dz/dv`` that reaches a few silhouette vertices is spread over their
neighbourhood (``dz/du = (I + λ L)^-T dz/dv``), and a step in ``u`` moves the surface smoothly.
λ is the job's ``geometry.largesteps_lambda``. ``N'`` is ``N`` less the duplicates that
``LargeSteps`` merges (a vertex repeated at a UV seam), so the parameter holds ``3 N'`` scalars;
the vertices written into the scene are ``from_differential(u)`` (``3 N``, gathered back).

Only Mitsuba's projective integrators differentiate the silhouettes that the vertices move
(``services.solver.estimators.methods.projective``). Beside the parameter itself this module
gives what a shape job reports: the Chamfer distance to a target mesh (:func:`chamfer`) and the
mesh as a PLY file (:func:`ply_bytes`).
"""

from __future__ import annotations

import base64
from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

#: The key suffix of a shape parameter.
VERTICES = "vertex_positions"
#: Rows of the first mesh per block of :func:`chamfer`'s distance matrix (memory: rows x M floats).
CHAMFER_ROWS = 256


def shape_of(key: str) -> str | None:
    """The shape id of a shape key ``<shape id>.vertex_positions``, else None."""
    suffix = "." + VERTICES
    return key[: -len(suffix)] if key.endswith(suffix) and len(key) > len(suffix) else None


@dataclass
class ShapeMesh:
    """One mesh whose vertices are optimized: its vertices as loaded ``v0`` ``(N, 3)``, its faces
    ``(F, 3)``, the ``LargeSteps`` solver of λ, the current differential coordinates ``value``
    (a Dr.Jit ``Float`` of ``3 N'``, which may be a gradient-tracking leaf) and, with a synthetic
    target mesh, its vertices ``target`` ``(M, 3)``."""

    shape: str
    v0: np.ndarray
    faces: np.ndarray
    lambda_: float
    steps: Any                 # mi.ad.LargeSteps (untyped)
    value: Any = None
    target: np.ndarray | None = field(default=None, repr=False)

    @classmethod
    def of(cls, params: mi.SceneParameters, shape: str, lambda_: float) -> ShapeMesh:
        positions = params[f"{shape}.{VERTICES}"]
        faces = params[f"{shape}.faces"]
        steps = mi.ad.LargeSteps(mi.Float(positions), mi.UInt(faces), lambda_)
        mesh = cls(shape, np.asarray(positions, np.float64).reshape(-1, 3),
                   np.asarray(faces, np.int64).reshape(-1, 3), lambda_, steps)
        mesh.value = mi.Float(mesh.steps.to_differential(mi.Float(positions)))
        dr.make_opaque(mesh.value)
        return mesh

    @property
    def size(self) -> int:
        """Scalars of the parameter, ``3 N'``."""
        return 3 * int(self.steps.n_verts)

    @property
    def centre(self) -> np.ndarray:
        return (self.v0.min(axis=0) + self.v0.max(axis=0)) / 2

    @property
    def radius(self) -> float:
        """The largest distance of a vertex as loaded from its bounding box's centre (scene units)."""
        return float(np.max(np.linalg.norm(self.v0 - self.centre, axis=1))) if len(self.v0) else 0.0

    def to_differential(self, vertices: np.ndarray) -> np.ndarray:
        """``u`` ``(3 N',)`` float64 of vertices ``(N, 3)``."""
        u = self.steps.to_differential(mi.Float(np.asarray(vertices, np.float32).ravel()))
        return np.asarray(u, np.float64)

    def vertices(self, u: np.ndarray) -> np.ndarray:
        """The vertices ``(N, 3)`` float64 of differential coordinates ``u`` ``(3 N',)`` (detached)."""
        v = self.steps.from_differential(mi.Float(np.asarray(u, np.float32).ravel()))
        return np.asarray(v, np.float64).reshape(-1, 3)

    def write(self, params: mi.SceneParameters) -> None:
        """Set the mesh's ``vertex_positions`` to ``from_differential(value)`` (differentiably: a
        gradient-tracking ``value`` gets ``dz/du``); the caller calls ``params.update()``."""
        params[f"{self.shape}.{VERTICES}"] = self.steps.from_differential(self.value)

    def report(self, u: np.ndarray) -> dict:
        """What a record says of the mesh at ``u``: vertices, faces and, against a target, the
        Chamfer distance (scene units)."""
        out: dict = {"vertices": len(self.v0), "faces": len(self.faces)}
        if self.target is not None:
            out["chamfer"] = chamfer(self.vertices(u), self.target)
        return out

    def final(self, u: np.ndarray) -> dict:
        """:meth:`report` with the mesh at ``u`` as ``ply``: base64 of :func:`ply_bytes`."""
        return {**self.report(u), "ply": base64.b64encode(ply_bytes(self.vertices(u), self.faces)).decode("ascii")}


class MeshReports:
    """What :class:`~services.solver.scene.params.ParameterSet` says of its optimized meshes (a
    mixin over its ``keys``, ``sizes`` and ``shapes``): where each parameter sits in the flat
    vector ``p`` and each mesh at a given ``p``."""

    keys: list[str]
    shapes: dict[str, ShapeMesh]
    poses: dict                     # shape id -> ShapePose (services.solver.scene.geometry)
    params: mi.SceneParameters

    @property
    def sizes(self) -> list[int]:
        raise NotImplementedError

    def _mesh(self, key: str) -> ShapeMesh | None:
        """The optimized mesh of a shape key, else None."""
        shape = shape_of(key)
        return self.shapes.get(shape) if shape is not None else None

    def offsets(self) -> dict[str, tuple[int, int]]:
        """``{key: (start, stop)}``: each parameter's entries of the flat vector ``p``."""
        ends = np.cumsum([0, *self.sizes])
        return {key: (int(ends[i]), int(ends[i + 1])) for i, key in enumerate(self.keys)}

    def shape_spans(self) -> list[tuple[int, int]]:
        """``(start, stop)`` in ``p`` of each shape parameter (a mesh's vertices)."""
        return [span for key, span in self.offsets().items() if self._mesh(key) is not None]

    def flat_meshes(self) -> list[str]:
        """The posed or reshaped meshes without vertex normals (flat-shaded: their shading jumps at
        every edge between two triangles), by shape id."""
        return sorted(shape for shape in set(self.poses) | set(self.shapes)
                      if f"{shape}.vertex_normals" not in self.params.keys()   # noqa: SIM118 (not a dict)
                      or dr.width(self.params[f"{shape}.vertex_normals"]) == 0)

    def shape_reports(self, values: np.ndarray, final: bool = False) -> dict[str, dict]:
        """Each optimized mesh at ``values`` (:meth:`.ShapeMesh.report`; ``final``: with its PLY,
        :meth:`.ShapeMesh.final`), by shape id."""
        spans = self.offsets()
        return {shape: (mesh.final if final else mesh.report)(values[slice(*spans[f"{shape}.vertex_positions"])])
                for shape, mesh in self.shapes.items()}


def write_topology(params: mi.SceneParameters, shape: str, vertices: np.ndarray, faces: np.ndarray) -> None:
    """Give the scene's mesh ``shape`` new triangles: ``vertices`` ``(N', 3)`` (world space) and
    ``faces`` ``(F', 3)``, whatever ``N'`` and ``F'`` (Mitsuba rebuilds the mesh and its
    acceleration structure on ``params.update()``, which this calls). Texture coordinates are
    dropped (they belonged to the old triangles); a mesh with vertex normals gets them recomputed
    from the new triangles."""
    vertices = np.asarray(vertices, np.float32).reshape(-1, 3)
    normals = f"{shape}.vertex_normals"
    smooth = normals in params.keys() and dr.width(params[normals]) > 0   # noqa: SIM118 (not a dict)
    params[f"{shape}.faces"] = mi.UInt(np.asarray(faces, np.uint32).ravel())
    params[f"{shape}.{VERTICES}"] = mi.Float(vertices.ravel())
    if normals in params.keys():   # noqa: SIM118
        params[normals] = mi.Float(np.zeros(3 * len(vertices) if smooth else 0, np.float32))
    if f"{shape}.vertex_texcoords" in params.keys():   # noqa: SIM118
        params[f"{shape}.vertex_texcoords"] = mi.Float()
    params.update()
    if smooth:
        params.properties[f"{shape}.{VERTICES}"][2].recompute_vertex_normals()   # the mesh (value, type, node, flags)


def chamfer(a: np.ndarray, b: np.ndarray) -> float:
    """The symmetric Chamfer distance of two point sets ``a`` ``(N, 3)`` and ``b`` ``(M, 3)``: the
    mean over ``a`` of the distance to the nearest point of ``b`` and the same from ``b``,
    averaged (scene units; 0 for equal sets). Exact, in blocks of :data:`CHAMFER_ROWS` rows of
    the ``N x M`` distance matrix (about a second for 10,000 vertices each)."""
    a, b = np.asarray(a, np.float64).reshape(-1, 3), np.asarray(b, np.float64).reshape(-1, 3)
    if not len(a) or not len(b):
        raise ValueError("the Chamfer distance needs two non-empty point sets")
    b2 = np.einsum("ij,ij->i", b, b)
    to_b = np.empty(len(a))
    to_a = np.full(len(b), np.inf)
    for start in range(0, len(a), CHAMFER_ROWS):
        rows = a[start:start + CHAMFER_ROWS]
        d2 = np.einsum("ij,ij->i", rows, rows)[:, None] + b2[None, :] - 2.0 * rows @ b.T
        np.maximum(d2, 0.0, out=d2)
        to_b[start:start + len(rows)] = d2.min(axis=1)
        np.minimum(to_a, d2.min(axis=0), out=to_a)
    return float(0.5 * (np.sqrt(to_b).mean() + np.sqrt(to_a).mean()))


def ply_bytes(vertices: np.ndarray, faces: np.ndarray) -> bytes:
    """A binary little-endian PLY of ``vertices`` ``(N, 3)`` (float32 x, y, z) and triangles
    ``faces`` ``(F, 3)`` (``vertex_indices``, a list of 3 int32): what Mitsuba's ``ply`` shape
    loads."""
    vertices = np.ascontiguousarray(np.asarray(vertices, "<f4").reshape(-1, 3))
    faces = np.asarray(faces, "<i4").reshape(-1, 3)
    header = ("ply\nformat binary_little_endian 1.0\ncomment written by ndrf (a recovered mesh)\n"
              f"element vertex {len(vertices)}\nproperty float x\nproperty float y\nproperty float z\n"
              f"element face {len(faces)}\nproperty list uchar int vertex_indices\nend_header\n")
    rows = np.empty(len(faces), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rows["n"], rows["i"] = 3, faces
    return header.encode("ascii") + vertices.tobytes() + rows.tobytes()


def read_ply(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """The vertices ``(N, 3)`` and faces ``(F, 3)`` of a PLY written by :func:`ply_bytes`."""
    end = data.index(b"end_header\n") + len(b"end_header\n")
    counts = {line.split()[1]: int(line.split()[2]) for line in data[:end].decode("ascii").splitlines()
              if line.startswith("element")}
    n, f = counts["vertex"], counts["face"]
    vertices = np.frombuffer(data, "<f4", 3 * n, end).reshape(n, 3)
    rows = np.frombuffer(data, [("n", "u1"), ("i", "<i4", (3,))], f, end + 12 * n)
    if np.any(rows["n"] != 3):
        raise ValueError("only triangles are read")
    return vertices.astype(np.float64), rows["i"].astype(np.int64)

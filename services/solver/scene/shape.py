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
gives what a shape job reports: the Chamfer distance to a target surface of any topology
(:func:`chamfer`) and the mesh as a PLY file (:func:`ply_bytes`).

A synthetic target (:class:`Surface`) of the mesh's own topology is rendered by assigning its
differential coordinates; one of another topology has none (its span of the target values is
NaN) and is rendered by swapping the mesh's topology to it for a while (:meth:`ShapeMesh.showing`,
:meth:`MeshReports.showing_targets`).
"""

from __future__ import annotations

import base64
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from typing import Any

import drjit as dr
import mitsuba as mi
import numpy as np

#: The key suffix of a shape parameter.
VERTICES = "vertex_positions"
#: Points sampled on each surface by :func:`chamfer` (uniform by area).
CHAMFER_POINTS = 30_000
#: The seed of :func:`chamfer`'s points: the same surfaces give the same distance.
CHAMFER_SEED = 0
#: The mesh attributes a topology swap (:meth:`ShapeMesh.showing`) writes and restores.
TOPOLOGY = ("faces", VERTICES, "vertex_normals", "vertex_texcoords")


@dataclass(frozen=True, eq=False)
class Surface:
    """A triangle mesh: ``vertices`` ``(M, 3)`` float64 (scene units) and ``faces`` ``(G, 3)``
    int64 indices into them."""

    vertices: np.ndarray
    faces: np.ndarray

    @classmethod
    def of(cls, vertices, faces) -> Surface:
        """The surface of array-likes, checked: ``(M, 3)`` finite vertices, ``(G, 3)`` faces indexing them."""
        v = np.asarray(vertices, np.float64).reshape(-1, 3)
        f = np.asarray(faces, np.int64).reshape(-1, 3)
        if not len(v) or not len(f):
            raise ValueError(f"a surface needs vertices and triangles, got {len(v)} and {len(f)}")
        if not np.all(np.isfinite(v)):
            raise ValueError("a surface's vertices must be finite")
        if f.min() < 0 or f.max() >= len(v):
            raise ValueError(f"a surface's faces index {len(v)} vertices, got indices {f.min()}..{f.max()}")
        return cls(v, f)


def shape_of(key: str) -> str | None:
    """The shape id of a shape key ``<shape id>.vertex_positions``, else None."""
    suffix = "." + VERTICES
    return key[: -len(suffix)] if key.endswith(suffix) and len(key) > len(suffix) else None


@dataclass
class ShapeMesh:
    """One mesh whose vertices are optimized: its vertices as loaded ``v0`` ``(N, 3)``, its faces
    ``(F, 3)``, the ``LargeSteps`` solver of λ, the current differential coordinates ``value``
    (a Dr.Jit ``Float`` of ``3 N'``, which may be a gradient-tracking leaf) and, with a synthetic
    target shape, its :class:`Surface` ``target`` (any topology)."""

    shape: str
    v0: np.ndarray
    faces: np.ndarray
    lambda_: float
    steps: Any                 # mi.ad.LargeSteps (untyped)
    value: Any = None
    target: Surface | None = field(default=None, repr=False)

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

    @contextmanager
    def showing(self, params: mi.SceneParameters, surface: Surface) -> Iterator[None]:
        """The scene's mesh swapped to ``surface`` for the block (:func:`write_topology`: a
        smooth-shaded mesh's target is smooth-shaded too), then restored to the arrays it held
        before (faces, vertices, normals, texture coordinates). Nothing may update ``params``
        through the :class:`ParameterSet` inside: its update writes ``from_differential(value)``,
        of the mesh's own vertex count."""
        keys = [f"{self.shape}.{name}" for name in TOPOLOGY]
        held = {key: type(params[key])(params[key]) for key in keys}      # copies of what the mesh holds
        write_topology(params, self.shape, surface.vertices, surface.faces)
        try:
            yield
        finally:
            for key, value in held.items():
                params[key] = value
            params.update()

    def report(self, u: np.ndarray) -> dict:
        """What a record says of the mesh at ``u``: vertices, faces and, against a target, the
        Chamfer distance (:func:`chamfer`, scene units)."""
        out: dict = {"vertices": len(self.v0), "faces": len(self.faces)}
        if self.target is not None:
            out["chamfer"] = chamfer(Surface(self.vertices(u), self.faces), self.target)
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

    def assign(self, values: np.ndarray) -> None:
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

    @contextmanager
    def showing_targets(self, target: np.ndarray) -> Iterator[None]:
        """The scene at the synthetic target ``target`` ``(P,)`` for the block: every parameter
        assigned its target value, then each mesh whose target has another topology (its span of
        ``target`` is NaN, there are no differential coordinates of it) swapped to its target
        surface (:meth:`ShapeMesh.showing`; such a mesh keeps its current ``value`` meanwhile).
        On exit the meshes are restored; the parameters stay at the target's values until the
        caller assigns others (nothing may assign inside the block)."""
        values = np.array(target, np.float64).reshape(-1)
        spans = self.offsets()
        swapped: list[tuple[ShapeMesh, Surface]] = []
        for shape, mesh in self.shapes.items():
            span = slice(*spans[f"{shape}.{VERTICES}"])
            if np.isnan(values[span]).any():
                if mesh.target is None:
                    raise ValueError(f"{shape}: the target values hold no vertices and there is no target surface")
                values[span] = np.asarray(mesh.value, np.float64)
                swapped.append((mesh, mesh.target))
        self.assign(values)
        with ExitStack() as stack:
            for mesh, surface in swapped:
                stack.enter_context(mesh.showing(self.params, surface))
            yield

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


def chamfer(a: Surface, b: Surface, points: int = CHAMFER_POINTS, seed: int = CHAMFER_SEED) -> float:
    """The symmetric Chamfer distance of surfaces ``a`` and ``b`` (scene units): the mean distance
    to ``b`` of points uniform by area on ``a``, plus the same from ``b`` to ``a``, halved. 0 for
    the same surface whatever its tessellation; ``d`` for two concentric spheres ``d`` apart.

    Estimated with ``points`` points per surface (``gpytoolbox.random_points_on_mesh``, a fresh
    generator seeded ``seed`` on each side, so the same surfaces give the same number and
    ``chamfer(a, b) == chamfer(b, a)``); each distance is exact, point to nearest triangle
    (``gpytoolbox.squared_distance``, an AABB tree). The Monte Carlo error of the default
    30,000 points, measured as the standard deviation over seeds relative to the mean: 0.37%
    (20 seeds) for the icosphere of ``shape-sphere`` against ``examples/shape.json``'s target
    (Chamfer 0.087), 0.36% (10 seeds) for the 35,947-vertex Stanford bunny against itself
    stretched by 10% along x (0.0020); with 100,000 points 0.24% and 0.42% of similar pairs.
    Seconds on the 2-core CPU: 0.06 for two 642-vertex meshes, 0.27 for two of 35,947 vertices
    (0.24 and 0.7 with 100,000 points, which every record of a shape job paid)."""
    import gpytoolbox

    def one_way(source: Surface, to: Surface) -> float:
        samples = gpytoolbox.random_points_on_mesh(source.vertices, source.faces, points,
                                                   rng=np.random.default_rng(seed))
        squared = gpytoolbox.squared_distance(samples, to.vertices, to.faces, use_cpp=True)[0]
        return float(np.sqrt(np.maximum(squared, 0.0)).mean())

    if points < 1:
        raise ValueError(f"the Chamfer distance needs at least one point per surface, got {points}")
    return 0.5 * (one_way(a, b) + one_way(b, a))


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

"""``shape-sphere``: a built-in scene for shape jobs, and the target shapes a job may ask for.

The sphere (``sphere``) is a mesh the project generates (no file): an icosphere of radius
:data:`RADIUS` about :data:`CENTRE`, :data:`SUBDIVISIONS` times subdivided (642 shared vertices,
1,280 triangles), diffuse grey, under a constant environment and an area light, seen by
:data:`VIEWS` cameras of 32x32 around it. Its ``sphere.vertex_positions`` is what a shape job
recovers (:mod:`.shape`). Nothing in the scene reflects light onto it (it is convex, and there is
no floor), so direct illumination is its whole image and ``auto`` takes ``direct-projective``.

A synthetic target shape is a mesh deformed (:func:`deform`: a smooth radial bump, then a scaling
per axis, about the centre of its bounding box): the shape's own mesh, a mesh of a file, or one the
project generates, :func:`rounded_box` (a rounded cube on its own grid: another vertex count and
connectivity than the icosphere's).
"""

from __future__ import annotations

import math

import numpy as np

from services.solver.backend import use_mitsuba
from services.solver.scene.posed import diffuse_mesh

RADIUS = 0.4
CENTRE = np.array([0.0, 0.0, 0.0])
SUBDIVISIONS = 3
VIEWS = 6
#: The rounded box's exponent ``n`` (``|x|^n + |y|^n + |z|^n = 1``: 2 is a sphere, larger is boxier).
BOX_EXPONENT = 6.0
#: Grid segments along each edge of the rounded box's cube faces (``6 k^2 + 2`` vertices: 866).
BOX_SEGMENTS = 12


def icosphere(subdivisions: int = SUBDIVISIONS) -> tuple[np.ndarray, np.ndarray]:
    """The unit icosphere: vertices ``(N, 3)`` float64 on the unit sphere, faces ``(F, 3)``
    int64 wound outwards; ``N = 10 · 4^s + 2``, ``F = 20 · 4^s``."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    vertices = [[-1, t, 0], [1, t, 0], [-1, -t, 0], [1, -t, 0], [0, -1, t], [0, 1, t], [0, -1, -t], [0, 1, -t],
                [t, 0, -1], [t, 0, 1], [-t, 0, -1], [-t, 0, 1]]
    faces = [[0, 11, 5], [0, 5, 1], [0, 1, 7], [0, 7, 10], [0, 10, 11], [1, 5, 9], [5, 11, 4], [11, 10, 2],
             [10, 7, 6], [7, 1, 8], [3, 9, 4], [3, 4, 2], [3, 2, 6], [3, 6, 8], [3, 8, 9], [4, 9, 5],
             [2, 4, 11], [6, 2, 10], [8, 6, 7], [9, 8, 1]]
    points = [np.asarray(v, np.float64) / np.linalg.norm(v) for v in vertices]
    middle: dict[tuple[int, int], int] = {}      # the vertex halfway along each edge (an edge is split once)

    def mid(i: int, j: int) -> int:
        key = (min(i, j), max(i, j))
        if key not in middle:
            p = points[i] + points[j]
            points.append(p / np.linalg.norm(p))
            middle[key] = len(points) - 1
        return middle[key]

    for _ in range(subdivisions):
        middle.clear()
        refined = []
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            refined += [[a, ab, ca], [b, bc, ab], [c, ca, bc], [ab, bc, ca]]
        faces = refined
    return np.asarray(points), np.asarray(faces, np.int64)


def rounded_box(segments: int = BOX_SEGMENTS, exponent: float = BOX_EXPONENT) -> tuple[np.ndarray, np.ndarray]:
    """A rounded cube about the origin, scaled so that its farthest point (its 8 corners, on the
    diagonals) is at distance 1: the superellipsoid ``|x|^n + |y|^n + |z|^n = a^n`` with ``n`` =
    ``exponent`` and half-side ``a = 3^(-1/3)`` (about 0.69), its faces nearly flat and its edges
    rounded. Tessellated on its own grid: each face of the cube ``[-1, 1]^3`` is cut into
    ``segments x segments`` squares of two triangles, the vertices shared along the cube's edges
    are merged, and every vertex is moved along its ray from the centre onto the surface.
    Returns vertices ``(6 k^2 + 2, 3)`` float64 and faces ``(12 k^2, 3)`` int64 wound outwards
    (``k = segments``)."""
    if segments < 1 or exponent < 2:
        raise ValueError(f"a rounded box needs segments >= 1 and exponent >= 2, got {segments}, {exponent}")
    ticks = np.linspace(-1.0, 1.0, segments + 1)
    u, v = (g.ravel() for g in np.meshgrid(ticks, ticks, indexing="ij"))
    corner = (np.arange(segments)[:, None] * (segments + 1) + np.arange(segments)[None, :]).ravel()
    quads = np.stack([corner, corner + segments + 1, corner + segments + 2, corner + 1], axis=1)
    points: list[np.ndarray] = []
    faces: list[np.ndarray] = []
    for axis in range(3):
        b, c = (axis + 1) % 3, (axis + 2) % 3      # e_b x e_c = e_axis: the grid's (u, v) wind outwards at +1
        for sign in (1.0, -1.0):
            grid = np.empty((len(u), 3))
            grid[:, axis], grid[:, b], grid[:, c] = sign, u, v if sign > 0 else -v
            quad = quads + len(u) * len(points)
            faces += [quad[:, [0, 1, 2]], quad[:, [0, 2, 3]]]
            points.append(grid)
    cube = np.concatenate(points)
    merged, index = np.unique(np.round(cube, 9), axis=0, return_inverse=True)
    faces_ = index.reshape(-1)[np.concatenate(faces)]
    on_surface = merged / (np.abs(merged) ** exponent).sum(axis=1, keepdims=True) ** (1.0 / exponent)
    on_surface /= np.linalg.norm(on_surface, axis=1).max()
    return on_surface, faces_.astype(np.int64)


def deform(vertices: np.ndarray, scale=(1.0, 1.0, 1.0), bump: float = 0.0, direction=(0.0, 1.0, 0.0),
           width: float = 0.5) -> np.ndarray:
    """Vertices ``(N, 3)`` moved about the centre ``c`` of their bounding box: first a smooth
    radial bump of height ``bump`` radii ``r`` towards ``direction`` (a vertex at angle ``θ`` from
    it moves out by ``bump · r · exp(-(θ / width)^2)``, ``width`` in radians), then scaled by
    ``scale`` per axis. Returns ``(N, 3)`` float64."""
    v = np.asarray(vertices, np.float64).reshape(-1, 3)
    centre = (v.min(axis=0) + v.max(axis=0)) / 2
    offset = v - centre
    length = np.linalg.norm(offset, axis=1)
    radius = float(length.max()) if len(v) else 0.0
    if bump:
        axis = np.asarray(direction, np.float64) / max(float(np.linalg.norm(direction)), 1e-12)
        unit = offset / np.maximum(length, 1e-12)[:, None]
        theta = np.arccos(np.clip(unit @ axis, -1.0, 1.0))
        offset = offset + (bump * radius * np.exp(-(theta / width) ** 2))[:, None] * unit
    return centre + offset * np.asarray(scale, np.float64)


def sphere_mesh(name: str = "sphere", subdivisions: int = SUBDIVISIONS, reflectance=(0.6, 0.6, 0.6)):
    """The icosphere as a Mitsuba mesh of radius :data:`RADIUS` about :data:`CENTRE`, smooth-shaded
    (vertex normals): flat-shaded, every edge between two triangles would be a jump in its shading,
    whose motion no projective integrator differentiates (``docs/guide/geometry.md``)."""
    points, faces = icosphere(subdivisions)
    return diffuse_mesh(name, points * RADIUS + CENTRE, faces, reflectance, smooth=True)


def shape_sphere_builtin(resolution: int = 32) -> dict:
    """The scene (module docstring): :data:`VIEWS` cameras every 60 degrees about the vertical
    axis, 20 degrees above the horizon."""
    mi = use_mitsuba()
    T = mi.ScalarTransform4f
    scene: dict = {"type": "scene", "integrator": {"type": "direct"}}
    for i in range(VIEWS):
        azimuth, elevation, distance = 2 * math.pi * i / VIEWS, math.radians(20), 2.0
        origin = [distance * math.cos(elevation) * math.sin(azimuth), distance * math.sin(elevation),
                  distance * math.cos(elevation) * math.cos(azimuth)]
        scene[f"view-{i}"] = {
            "type": "perspective", "fov": 35,
            "to_world": T().look_at(origin=origin, target=CENTRE.tolist(), up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": resolution, "height": resolution, "rfilter": {"type": "box"},
                     "sample_border": True},
            "sampler": {"type": "independent", "sample_count": 16}}
    scene["sphere"] = sphere_mesh()
    scene["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}
    scene["light"] = {"type": "rectangle", "to_world": T().look_at(origin=[1.0, 1.5, 1.0], target=[0, 0, 0],
                                                                   up=[0, 1, 0]).scale(0.3),
                      "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [15.0, 15.0, 15.0]}}}
    return scene

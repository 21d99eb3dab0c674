"""Remeshing a shape parameter's mesh: Botsch-Kobbelt isotropic remeshing (Botsch & Kobbelt
2004, "A remeshing approach to multiresolution modeling"), what Mitsuba's shape tutorial runs
between its two stages, through ``gpytoolbox.remesh_botsch``.

A mesh optimized from a coarse start keeps the triangles it was loaded with: stretched where the
surface grew, too coarse for the detail the views show. Remeshing replaces them with triangles
of a target edge length ``h``: each pass splits edges longer than ``4/3 h``, collapses those
shorter than ``4/5 h``, flips edges towards valence 6 and relaxes the vertices tangentially,
projected back onto the surface being remeshed, so the shape is kept and only its tessellation
changes. The run then continues on the new vertices (``services.solver.optimize.remeshing``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Remeshed:
    """A remeshed mesh: ``vertices`` ``(N', 3)`` float64 and ``faces`` ``(F', 3)`` int64, from a
    mesh of ``before`` vertices with target edge length ``edge`` (scene units)."""

    vertices: np.ndarray
    faces: np.ndarray
    before: int
    edge: float


def mean_edge(vertices: np.ndarray, faces: np.ndarray) -> float:
    """The mean length of a triangle mesh's edges, each triangle's three counted (an interior
    edge twice, as the tutorial computes it): ``vertices`` ``(N, 3)``, ``faces`` ``(F, 3)``."""
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    lengths = [np.linalg.norm(v[f[:, i]] - v[f[:, (i + 1) % 3]], axis=1) for i in range(3)]
    return float(np.mean(lengths))


def remesh(vertices: np.ndarray, faces: np.ndarray, edge_ratio: float, passes: int) -> Remeshed:
    """Remesh ``vertices`` ``(N, 3)``, ``faces`` ``(F, 3)`` to edges of ``edge_ratio`` times
    their mean length, in ``passes`` passes, projected onto the input surface. Raises
    ``ValueError`` when the input is empty or the result is not a finite triangle mesh."""
    if not edge_ratio > 0:
        raise ValueError(f"edge_ratio must be > 0, got {edge_ratio}")
    if passes < 1:
        raise ValueError(f"passes must be >= 1, got {passes}")
    v = np.ascontiguousarray(np.asarray(vertices, np.float64).reshape(-1, 3))
    f = np.ascontiguousarray(np.asarray(faces, np.int64).reshape(-1, 3)).astype(np.int32)
    if not len(v) or not len(f):
        raise ValueError("an empty mesh cannot be remeshed")
    from gpytoolbox import remesh_botsch  # a compiled library: loaded by the jobs that remesh only

    h = edge_ratio * mean_edge(v, f)
    new_v, new_f = remesh_botsch(v, f, i=int(passes), h=h, project=True)
    new_v, new_f = np.asarray(new_v, np.float64), np.asarray(new_f, np.int64)
    if not len(new_f) or not np.all(np.isfinite(new_v)) or new_f.min() < 0 or new_f.max() >= len(new_v):
        raise ValueError(f"remeshing to edges of {h:.4g} gave no valid triangle mesh ({len(new_v)} vertices, "
                         f"{len(new_f)} triangles)")
    return Remeshed(new_v, new_f, len(v), h)


def expected_vertices(vertices: int, edge_ratio: float, remeshes: int) -> int:
    """Roughly the vertices after ``remeshes`` remeshings of a mesh of ``vertices`` at
    ``edge_ratio``: a triangle's area scales with its edge squared, so each multiplies the count
    by ``1 / edge_ratio^2`` (measured: 642 -> 2,435-2,520 at 0.5 on the built-in sphere). The
    surface's own growth during the run comes on top."""
    return int(round(vertices / edge_ratio ** (2 * remeshes)))

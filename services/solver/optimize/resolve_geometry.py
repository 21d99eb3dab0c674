"""What :func:`services.solver.optimize.resolve.resolve` decides for a job that moves a shape (a
pose, a mesh's vertices): the method, a mesh's optimizer and the curvature of a pose's
second-order steps (the rules are listed in that module's docstring; the loss's blur is
:mod:`.blur`'s)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from schemas.job import JobSpec
from schemas.methods import AUTO, Method
from services.solver.optimize.recipe import Remesh

if TYPE_CHECKING:
    from services.solver.estimators.render import PathDepth


class Measures(Protocol):
    """What :func:`geometry_method` measures (of :class:`services.solver.optimize.resolve.Measures`)."""

    def missing_energy(self, depth: PathDepth) -> float:
        """The share of the image's light a truncated path ``depth`` misses."""


def geometry_method(spec: JobSpec, measures: Measures, decide, *, direct: PathDepth, limit: float) -> str:
    """The method of a job that moves a shape: the job's (which the validate stage has checked
    can differentiate a moving silhouette, :func:`~.validate.check_geometry`), or ``auto``'s
    projective integrator:
    ``direct-projective`` where paths longer than ``direct`` carry at most ``limit`` of the light."""
    if spec.method != AUTO:
        return str(spec.method)
    missing = measures.missing_energy(direct)
    share = f"paths longer than direct illumination carry {missing:.2%} of the image's light"
    if missing <= limit:
        decide("method", str(Method.DIRECT_PROJECTIVE),
               f"geometry (a shape's pose) needs the boundary term of moving silhouettes, which Mitsuba's projective "
               f"integrators sample; {share} (at most {limit:.1%}): direct illumination is the image")
        return str(Method.DIRECT_PROJECTIVE)
    decide("method", str(Method.PRB_PROJECTIVE),
           f"geometry (a shape's pose) needs the boundary term of moving silhouettes, which Mitsuba's projective "
           f"integrators sample; {share} (more than {limit:.1%}): every bounce, or the candidates would "
           f"miss light the targets have")
    return str(Method.PRB_PROJECTIVE)


def shape_optimizer(spec: JobSpec, spans: tuple[tuple[int, int], ...], decide) -> str:
    """Adam, uniform per mesh, for a job that optimizes a mesh's vertices (module docstring; the
    validate stage has refused a second-order optimizer, :func:`~.validate.check_geometry`)."""
    scalars = sum(stop - start for start, stop in spans)
    decide("optimizer", "adam", f"a mesh's vertices: {scalars} LargeSteps coordinates, whose Jacobian would cost one "
                                f"forward render each per view; Adam on the adjoint gradient, one step scale per mesh "
                                f"(uniform: the largest second moment, as mi.ad.Adam(uniform=True) in Mitsuba's shape "
                                f"tutorial)" + ("" if spec.optimizer == "auto" else " (the job's optimizer)"))
    return "adam"


def curvature(spec: JobSpec, optimizer: str, blurred_pose: bool, decide) -> str:
    """The job's ``hessian``, ``auto`` resolved: ``cross`` for the second-order steps of a pose
    whose loss is blurred (:mod:`.blur`: films of 48 px and more), else ``successive``."""
    if spec.hessian != "auto":
        return spec.hessian
    if blurred_pose and optimizer != "adam":
        decide("curvature", "cross", "a pose on a blurred loss: its Jacobian changes as the silhouettes move, so the "
                                     "successive curvature would mostly fall back to the product, which J's noise "
                                     "biases upwards and which shortens the steps; two independent Jacobians per view "
                                     "instead (on the bunny at 64x64: 2.0 degrees in 20 iterations where successive "
                                     "left 9.9)")
        return "cross"
    return "successive"


def remesh_schedule(spec: JobSpec, decide) -> Remesh | None:
    """The job's remeshing schedule (``geometry.remesh_at``; the schema has checked that the job
    optimizes a mesh's vertices and that every remesh comes before an iteration), None without."""
    geometry = spec.geometry
    if not geometry.remesh_at:
        return None
    at = tuple(geometry.remesh_at)
    decide("remesh", ", ".join(map(str, at)),
           f"the job's geometry.remesh_at: before these iterations every optimized mesh is remeshed (Botsch-Kobbelt, "
           f"{geometry.remesh_passes} passes) to edges of {geometry.remesh_edge:g} times its mean edge length, and the "
           f"optimizer, its learning-rate decay and the answer start again on the new vertices")
    return Remesh(at, geometry.remesh_edge, geometry.remesh_passes)


def flat_shading_warning(flat: list[str]) -> str | None:
    """What a geometry job's flat-shaded meshes (``flat``: shape ids without vertex normals) cost,
    or None. Their shading jumps at every edge between two triangles; the edges move with the
    vertices, and the projective integrators sample the boundary terms of visibility (silhouettes,
    shadows) only: the gradient misses those jumps' motion."""
    if not flat:
        return None
    return (f"{', '.join(flat)}: flat-shaded (no vertex normals), so the shading jumps at every edge between two "
            f"triangles, and the projective integrators differentiate only visibility's discontinuities, not the motion "
            f"of these: the gradient falls short (on a flat-shaded icosphere 0.77 of finite differences, 0.95 with vertex "
            f"normals). A smooth surface's mesh should carry vertex normals (Mitsuba computes them for a PLY or OBJ "
            f"without, unless face_normals is set); a box's true edges stay flat, and their motion stays undifferentiated")

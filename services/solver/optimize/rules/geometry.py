"""A job that moves a shape (a pose, :mod:`services.solver.scene.geometry`; a mesh's vertices in
LargeSteps coordinates, :mod:`services.solver.scene.shape`): its method, a mesh's optimizer, the
units of a pose's steps, the curvature of a pose's second-order steps, the remeshing schedule and
what flat shading costs. Its views and samples are :mod:`.batch`'s, a pose's optimizer
:mod:`.optimizer`'s, the loss's blur :mod:`services.solver.optimize.blur`'s.

* **The method**: only Mitsuba's projective integrators differentiate a moving silhouette (the
  validate stage refuses every other method with the reason). ``auto`` takes
  ``direct-projective`` where paths longer than direct illumination (:data:`DIRECT_DEPTH`) carry
  at most :data:`~.depth.MISSING_ENERGY` of the image's light (measured,
  :func:`~services.solver.estimators.render.missing_energy`), else ``prb-projective``.
* **A pose's steps** are measured in its shape's size (:meth:`ParameterSet.step_units
  <services.solver.scene.params.ParameterSet.step_units>`): a degree is not a scene unit.
* **A mesh's vertices**: Adam with one step scale per mesh (``uniform``, as Mitsuba's shape
  tutorial): its ``3 N`` scalars would take one forward render each for a Jacobian, and per-entry
  scales would undo the parameterization's smoothing. The job's remeshing schedule
  (``geometry.remesh_at``) cuts the run into stages, each with its own learning-rate decay, and
  no stopping rule ends the run before its last stage.
"""

from __future__ import annotations

from schemas.job import JobSpec
from schemas.methods import AUTO, Method
from services.solver.estimators.render import PathDepth
from services.solver.optimize.recipe import Remesh
from services.solver.optimize.rules.depth import MISSING_ENERGY
from services.solver.optimize.rules.inputs import Decide, Measures, Parameters

#: The path depth of direct illumination (emitters seen and one bounce), what ``direct-projective`` renders.
DIRECT_DEPTH = PathDepth(2, None)


def geometry_method(spec: JobSpec, measures: Measures, decide: Decide) -> str:
    """The method of a job that moves a shape: the job's (which the validate stage has checked
    can differentiate a moving silhouette,
    :func:`~services.solver.optimize.validate.check_geometry`), or ``auto``'s projective
    integrator (module docstring)."""
    if spec.method != AUTO:
        return str(spec.method)
    limit = MISSING_ENERGY
    missing = measures.missing_energy(DIRECT_DEPTH)
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


def step_units(parameters: Parameters, decide: Decide) -> tuple[float, ...]:
    """Per scalar of a geometry job, one unit of the optimizer's steps in its own units (empty
    otherwise: all 1)."""
    units = tuple(float(u) for u in parameters.step_units()) if parameters.has_geometry else ()
    if any(u != 1.0 for u in units):
        decide("step_units", ", ".join(f"{u:.4g}" for u in sorted(set(units))),
               "a pose's steps are measured in its shape's size: a translation in the shape's radius, a rotation in "
               "radians (which move its farthest vertex by one radius), so that the learning rate and the trust "
               "region mean the same share of the shape for both (degrees are not scene units)")
    return units


def shape_optimizer(spec: JobSpec, spans: tuple[tuple[int, int], ...], decide: Decide) -> str:
    """Adam, uniform per mesh, for a job that optimizes a mesh's vertices (module docstring; the
    validate stage has refused a second-order optimizer,
    :func:`~services.solver.optimize.validate.check_geometry`)."""
    scalars = sum(stop - start for start, stop in spans)
    decide("optimizer", "adam", f"a mesh's vertices: {scalars} LargeSteps coordinates, whose Jacobian would cost one "
                                f"forward render each per view; Adam on the adjoint gradient, one step scale per mesh "
                                f"(uniform: the largest second moment, as mi.ad.Adam(uniform=True) in Mitsuba's shape "
                                f"tutorial)" + ("" if spec.optimizer == "auto" else " (the job's optimizer)"))
    return "adam"


def curvature(spec: JobSpec, optimizer: str, blurred_pose: bool, decide: Decide) -> str:
    """The job's ``hessian``, ``auto`` resolved: ``cross`` for the second-order steps of a pose
    whose loss is blurred (:mod:`services.solver.optimize.blur`: films of 48 px and more), else ``successive``."""
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


def remesh_schedule(spec: JobSpec, decide: Decide) -> Remesh | None:
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

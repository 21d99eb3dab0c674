"""The validate stage: everything wrong with a job that the schema alone cannot see, raised as
an :class:`InvalidJob` naming the field, before :func:`~.resolve.resolve` decides anything.

:func:`validate` runs once per job, in :func:`services.solver.optimize.setup.check`, which both
the service's preflight (at submission, in the sandbox) and every run call: a job the service
accepts resolves without an error, and ``resolve`` raises nothing (its rules only choose). The
schema (:mod:`schemas.job`) checks what one job file says alone (ranges, combinations of its own
fields); this stage checks the job against its scene's parameters:

* the sizes: listed scalars, texels, a mesh's vertices and what remeshing makes of them;
* what each gradient method and optimizer can carry (the table below), and the many-parameter
  head's constraints;
* geometry (a pose, a mesh's vertices): a moving silhouette has a boundary term only Mitsuba's
  projective integrators sample; a mesh's ``3 N`` vertices have no affordable Jacobian; a shape
  parameter starts from the scene's mesh;
* the Jacobian ``differential-field`` needs the ``dL_theta`` the job does not turn off.

What each gradient method and optimizer can carry:

=====================  =====================================================================
``prb``                any count: one adjoint render gives ``dz/dp`` for every scalar, texels
                       included (a texture's gradient is a texture, never P images)
``ndrf-rhs`` with      any count of BSDF scalars: ``dL_theta`` is the many-parameter head (R
``training.head``      basis functions, an R x P coefficient matrix; paper Sec. 8), dz/dp is one
                       adjoint pass plus ``Cᵀ v`` (``services.solver.estimators.methods.head``)
``ndrf-lhs/-rhs``      not textures: ``dL_theta`` has three outputs per scalar (its output
(no head)              layer grows with P; the paper's Sec. 8 limitation); ``ndrf-rhs`` with
                       ``training.head`` carries them
``direct``,            any count: dz/dp is a contraction at the camera hits and at one bounce,
``radiance-cache``     formed for a texture job by one adjoint pass through their own estimate
                       (``CameraHitMethod.adjoint_gradient``), never P images
``levenberg-marquardt``,  not textures: the steps solve with a P x P curvature (a 64 x 64
``gauss-newton``       texture: 12,288^2 doubles, 1.2 GB) from P Jacobian images per view
``jacobian:``          not textures: dL_theta (as above)
``differential-field``
=====================  =====================================================================

``auto`` takes ``prb`` with Adam for a job with a texture (:mod:`.rules.optimizer`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from schemas.errors import InvalidJob
from schemas.job import SECOND_ORDER, JobSpec
from schemas.methods import AUTO, Method
from services.solver.estimators.methods import method_class
from services.solver.scene.remesh import expected_vertices

if TYPE_CHECKING:
    from services.solver.optimize.textures import TextureReport
    from services.solver.scene.params import ParameterSet

#: Methods that carry any number of scalars, textures included.
ANY_COUNT = frozenset({Method.PRB, Method.DIRECT, Method.RADIANCE_CACHE})
#: Methods that carry them with ``training.head`` (the many-parameter head).
WITH_HEAD = frozenset({Method.NDRF_RHS})

_WHY = {
    Method.NDRF_LHS: "dL_theta has three outputs per scalar, so its output layer grows with the parameter count "
                     "(the paper's Sec. 8 limitation; the many-parameter head, training.head, serves ndrf-rhs only)",
    Method.NDRF_RHS: "dL_theta has three outputs per scalar, so its output layer grows with the parameter count "
                     "(the paper's Sec. 8 limitation); set training.head for the many-parameter head",
}


def validate(spec: JobSpec, parameters: ParameterSet, *, max_scalars: int | None = None,
             max_texels: int | None = None) -> None:
    """The validate stage (module docstring): raise the first :class:`InvalidJob` of ``spec``
    against its scene's optimized ``parameters``; ``max_scalars`` and ``max_texels`` are the
    service's caps (None: uncapped, as a local run)."""
    from services.solver.optimize.textures import TextureReport

    split = TextureReport(parameters)
    check_sizes(spec, split, {mesh.shape: mesh.size // 3 for mesh in parameters.shapes.values()},
                max_scalars=max_scalars, max_texels=max_texels)
    check_head(spec, [info.owner for info in parameters.infos])
    check_carry(spec, parameters.n, [t.key for t in split.textures])
    mesh_scalars = sum(mesh.size for mesh in parameters.shapes.values())
    check_geometry(spec, geometry=parameters.has_geometry, mesh_scalars=mesh_scalars)
    for i, (p, info) in enumerate(zip(spec.parameters, parameters.infos)):
        if p.key.endswith(".vertex_positions") and info.owner == "geometry" and (p.init, p.bounds) != (None, None):
            raise InvalidJob(f"parameters[{i}]", "a shape parameter starts from the scene's mesh and has no bounds "
                                                 "(its scalars are LargeSteps differential coordinates): leave init "
                                                 "and bounds unset")
    check_fields(spec)


def check_sizes(spec: JobSpec, split: TextureReport, vertices: dict[str, int], *, max_scalars: int | None,
                max_texels: int | None) -> None:
    """The caps on what the job optimizes: listed scalars (an RGB value counts 3), texels, and the
    optimized meshes' ``vertices`` (per shape id) with the textures' texels, before and after the
    job's remeshing (``geometry.remesh_at``: 1/edge^2 as many vertices each time)."""
    listed = int(split.listed.sum())
    if max_scalars is not None and listed > max_scalars:
        raise InvalidJob("parameters", f"{listed} scalars exceed the limit of {max_scalars} "
                                       f"(an RGB value counts 3; textures count by texel instead; NDRF_MAX_PARAMETERS)")
    if max_texels is None:
        return
    if split.texels > max_texels:
        raise InvalidJob("parameters", f"the textures have {split.texels} texels, more than the limit of {max_texels} "
                                       f"(NDRF_MAX_TEXELS)")
    total = sum(vertices.values())
    if split.texels + total > max_texels:
        raise InvalidJob("parameters", f"the optimized meshes have {total} vertices (and the textures "
                                       f"{split.texels} texels), more than the limit of {max_texels} together "
                                       f"(NDRF_MAX_TEXELS)")
    geometry = spec.geometry
    remeshed = sum(expected_vertices(count, geometry.remesh_edge, len(geometry.remesh_at))
                   for count in vertices.values())
    if geometry.remesh_at and split.texels + remeshed > max_texels:
        raise InvalidJob("geometry.remesh_edge", f"remeshing {len(geometry.remesh_at)} time(s) to edges of "
                                                 f"{geometry.remesh_edge} of their mean length gives the optimized "
                                                 f"meshes about {remeshed} vertices (from {total}: 1/edge^2 each "
                                                 f"time), more than the limit of {max_texels} with the textures' "
                                                 f"{split.texels} texels (NDRF_MAX_TEXELS)")


def check_carry(spec: JobSpec, scalars: int, textures: list[str]) -> None:
    """Raise :class:`InvalidJob` when the job's method, optimizer or Jacobian cannot carry its
    parameters: ``scalars`` optimized scalars of which the parameters ``textures`` are bitmap
    textures. Jobs without a texture are left as they are (the scalar cap applies to them)."""
    if not textures:
        return
    what = f"{scalars} scalars (texture {', '.join(textures)})"
    head = spec.training.head is not None and spec.method in WITH_HEAD
    if spec.method != AUTO and spec.method not in ANY_COUNT and not head:
        raise InvalidJob("method", f"method {spec.method!r} cannot carry {what}: {_WHY[Method(spec.method)]}; "
                                   f"use prb, direct or radiance-cache (or auto)")
    if spec.optimizer in SECOND_ORDER:
        gib = scalars * scalars * 8 / 2**30
        raise InvalidJob("optimizer", f"optimizer {spec.optimizer!r} cannot carry {what}: its steps solve with a "
                                      f"P x P curvature ({gib:.1f} GiB) from per-scalar Jacobian images; use adam "
                                      f"(or auto)")
    if spec.jacobian == "differential-field":
        raise InvalidJob("jacobian", f"jacobian 'differential-field' cannot carry {what}: {_WHY[Method.NDRF_LHS]}")


def check_head(spec: JobSpec, owners: list[str]) -> None:
    """Raise :class:`InvalidJob` when ``training.head`` (the many-parameter head) is set with a
    choice it does not serve; ``owners``: ``"bsdf"`` or ``"emitter"`` per parameter. The head
    serves ``ndrf-rhs`` with first-order steps, path-traced candidates, the method's own Jacobian
    and BSDF parameters (its exact local term is ``∂f``; ``∂E`` is not carried)."""
    if spec.training.head is None:
        return
    if spec.method not in WITH_HEAD:
        raise InvalidJob("training.head", f"training.head serves method ndrf-rhs only, not {spec.method!r}")
    if spec.jacobian != "method":
        raise InvalidJob("jacobian", "training.head: the Jacobian must be the method's own ('method')")
    if spec.optimizer in SECOND_ORDER:
        raise InvalidJob("optimizer", f"training.head: optimizer {spec.optimizer!r} needs P Jacobian images per "
                                      f"view; use adam")
    if spec.render.candidate != "path" or spec.render.first_hits != "fresh":
        raise InvalidJob("render", "training.head: render.candidate must be 'path' and render.first_hits "
                                   "'fresh' (the cached first hits serve ndrf-lhs)")
    emitters = [i for i, owner in enumerate(owners) if owner != "bsdf"]
    if emitters:
        raise InvalidJob(f"parameters[{emitters[0]}].key", "training.head carries BSDF parameters only (its exact "
                                                           "local term is the BSDF's derivative; dE is not carried)")


def check_geometry(spec: JobSpec, *, geometry: bool, mesh_scalars: int) -> None:
    """Raise :class:`InvalidJob` when a job that moves a shape (``geometry``: a pose or a mesh's
    vertices, ``mesh_scalars`` of them a mesh's) asks for what cannot differentiate it: a method
    without the boundary term of moving silhouettes, ``dL_theta``'s Jacobian (which has none), or
    a second-order optimizer over a mesh's vertices (one forward render per scalar and view)."""
    if not geometry:
        return
    if spec.method != AUTO:
        refusal = method_class(str(spec.method)).geometry_refusal
        if refusal is not None:
            raise InvalidJob("method", f"{spec.method} cannot optimize geometry (a shape's pose or vertices): "
                                       f"{refusal}; use prb-projective or direct-projective (or method auto)")
    if spec.jacobian == "differential-field":
        raise InvalidJob("jacobian", "jacobian 'differential-field' is dL_theta's, which has no boundary term for "
                                     "moving silhouettes: geometry takes the method's own Jacobian")
    if mesh_scalars and spec.optimizer in SECOND_ORDER:
        raise InvalidJob("optimizer", f"{spec.optimizer} needs the Jacobian of every scalar, and a mesh's vertices are "
                                      f"{mesh_scalars} scalars (one forward render each per view): use adam or auto")


def check_fields(spec: JobSpec) -> None:
    """Raise :class:`InvalidJob` when the Jacobian ``differential-field`` is asked for with the
    field it reads turned off (``effects.differential_field: off``). Where the scene turns it off
    (no light bounces between surfaces), :func:`~.resolve.resolve` takes the method's own Jacobian
    instead, with the reason: the job is valid, only its choice is moot."""
    if spec.jacobian == "differential-field" and spec.effects.differential_field == "off":
        raise InvalidJob("jacobian", "jacobian 'differential-field' reads dL_theta, and effects.differential_field "
                                     "turns it off: leave it auto (or on), or take the method's own Jacobian")

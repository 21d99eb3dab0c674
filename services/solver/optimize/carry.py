"""What each gradient method and optimizer can carry: a job whose parameters one of its choices
cannot carry is refused before it runs, with the reason (an :class:`InvalidJob` naming the field).

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

``auto`` takes ``prb`` with Adam for a job with a texture (``services.solver.optimize.recipe``).
"""

from __future__ import annotations

from schemas.errors import InvalidJob
from schemas.job import SECOND_ORDER, JobSpec
from schemas.methods import AUTO, Method

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

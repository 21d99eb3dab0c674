"""Residuals of the rendering equation (Eq. 5) and of the differential rendering equation (Eq. 6),
estimated by Monte Carlo over residual points and incident directions (Eq. 8, 9).

The fields represent reflected radiance (emission is added exactly where a ray meets an
emitter; see :mod:`services.solver.sampling.incident`), so at a residual point ``x`` (never an emitter)

    r_phi(x, ω_o)   = L_phi(x, ω_o)   - mean_M[ emitted + throughput · L_phi(x') ]                   (Eq. 5, 9)
    r_theta(x, ω_o) = dL_theta(x, ω_o) - mean_M[ ∂emitted + ∂throughput · sg(L_phi(x'))
                                                 + throughput · dL_theta(x') ]                       (Eq. 6, 9)

with ``sg`` the stop-gradient of Sec. 6.1: ``L_phi`` is a constant of the differential residual.
The two residuals use separate sample sets (Sec. 6.1). Shapes: ``N`` points, ``M`` incident
samples per point, ``P`` optimized scalars.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import torch

from services.solver.estimators.layout import DerivativeLayout
from services.solver.estimators.problem import Problem
from services.solver.fields.field import NeuralField
from services.solver.fields.query import FieldQuery
from services.solver.sampling.camera import camera_points, make_sampler
from services.solver.sampling.incident import IncidentGeometry, evaluate_incident, sample_geometry
from services.solver.sampling.tensors import field_query, flat, mask, rgb
from services.solver.seeds import derive_seed


@dataclass
class ResidualBatch:
    """``N`` residual points with ``M`` incident samples each (torch).

    points        FieldQuery (N)          where the left-hand side is evaluated
    weight        (N,)                    p_ref / p(x, ω_o) of Eq. 8
    emitted       (N, M, 3)               see services.solver.sampling.incident
    throughput    (N, M, 3)
    d_emitted     (N, M, A, 3) or None    derivatives w.r.t. the A active scalars (problem.layout)
    d_throughput  (N, M, A, 3) or None    None also when ∂f is not attached (no BSDF parameter)
    hit_index     (H,) long               incident samples whose x' is a surface of the domain
    hits          FieldQuery (H)          x' of those samples (where the fields are queried)
    """

    points: FieldQuery
    weight: torch.Tensor
    emitted: torch.Tensor
    throughput: torch.Tensor
    d_emitted: torch.Tensor | None
    d_throughput: torch.Tensor | None
    hit_index: torch.Tensor
    hits: FieldQuery
    sanitized: int

    @property
    def shape(self) -> tuple[int, int]:
        return self.emitted.shape[0], self.emitted.shape[1]


def _stack_derivatives(grads: list | None, n: int, m: int) -> torch.Tensor | None:
    """List of A Color3f (N·M lanes) -> (N, M, A, 3)."""
    if grads is None:
        return None
    if not grads:
        return torch.zeros(n, m, 0, 3)
    return torch.stack([rgb(g) for g in grads], 1).reshape(n, m, len(grads), 3)


def _points(problem: Problem, n: int, seed: int, camera_fraction: float):
    """``n`` residual points: a fraction where the cameras look (weight 1), the rest uniform by area
    and direction (Eq. 8). Weighting only moves the approximation error, not the fixed point: with
    zero residual everywhere both weightings agree; with a finite network, points where the
    gradient is queried (Eq. 11) matter most."""
    scene = problem.scene.scene
    wanted = int(round(n * camera_fraction))
    camera_si, kept = (None, 0)
    if wanted:
        sensor = problem.scene.sensor(seed % problem.scene.sensor_count)
        camera_si, kept = camera_points(scene, sensor, derive_seed(seed, "camera-points"), wanted, problem.delta_depth)
    uniform = problem.surface.sample(make_sampler(seed, n - kept), n - kept)
    if not kept:
        return uniform.si, uniform.weight
    lane = dr.arange(mi.UInt32, n)
    from_uniform = lane < (n - kept)
    si = dr.select(from_uniform, dr.gather(mi.SurfaceInteraction3f, uniform.si, dr.minimum(lane, n - kept - 1)),
                   dr.gather(mi.SurfaceInteraction3f, camera_si, dr.maximum(lane, n - kept) - (n - kept)))
    weight = dr.select(from_uniform, dr.gather(mi.Float, uniform.weight, dr.minimum(lane, n - kept - 1)), 1.0)
    return si, weight


@dataclass
class BatchGeometry:
    """The parameter-independent part of a residual batch: ``n`` points, ``m`` incident samples
    each (``n·m`` lanes of ``geometry``, point-major), and their field queries.

    points        FieldQuery (n)        hit_index  (H,) long: lanes whose x' is a surface of the domain
    weight        (n,)                  hits       FieldQuery (H)
    """

    n: int
    m: int
    geometry: IncidentGeometry
    points: FieldQuery
    weight: torch.Tensor
    hit_index: torch.Tensor
    hits: FieldQuery


def draw_geometry(problem: Problem, n: int, m: int, seed: int, camera_fraction: float = 0.0) -> BatchGeometry:
    """Sample ``n`` residual points (Eq. 8) and ``m`` incident directions each (Eq. 9), and trace
    them: everything of a batch that does not depend on BSDF or emitter values."""
    points_si, points_weight = _points(problem, n, seed, camera_fraction)
    lanes = dr.arange(mi.UInt32, n * m) // m
    si = dr.gather(mi.SurfaceInteraction3f, points_si, lanes)
    sampler = make_sampler(derive_seed(seed, "incident"), n * m)
    geometry = sample_geometry(problem.scene.scene, si, sampler, delta_depth=problem.delta_depth)
    geometry.schedule()
    hit_index, hits = field_query(geometry.hit).compact(mask(geometry.hit_surface))
    weight = flat(points_weight, n).clone()  # (n,): a literal weight is one lane wide
    return BatchGeometry(n, m, geometry, field_query(points_si), weight, hit_index, hits)


def evaluate_batch(problem: Problem, g: BatchGeometry, derivatives: bool) -> ResidualBatch:
    """The BSDF and emitter values of Eq. 9 on ``g`` for the scene's current parameters; with
    ``derivatives``, also their forward-mode derivatives w.r.t. the active scalars (for Eq. 6)."""
    scene, n, m = problem.scene.scene, g.n, g.m
    params = problem.parameters if derivatives else None
    bsdf, emission = problem.attach_bsdf, problem.attach_emission
    if params is not None:
        with params.tracking():
            inc = evaluate_incident(scene, g.geometry, parameters=params, scalars=problem.layout.scalars,
                                    attach_bsdf=bsdf, attach_emission=emission)
    else:
        inc = evaluate_incident(scene, g.geometry, attach_bsdf=bsdf, attach_emission=emission)
    problem.count_sanitized("residual", inc.sanitized)
    hit_index, hits = g.hit_index, g.hits
    if inc.sanitized:  # lanes zeroed by the guard are no longer queried
        keep = mask(inc.hit_surface)[hit_index]
        hit_index, hits = hit_index[keep], hits.select(torch.nonzero(keep).squeeze(1))
    return ResidualBatch(
        points=g.points,
        weight=g.weight,
        emitted=rgb(inc.emitted).reshape(n, m, 3),
        throughput=rgb(inc.throughput).reshape(n, m, 3),
        d_emitted=_stack_derivatives(inc.d_emitted, n, m) if params is not None else None,
        d_throughput=_stack_derivatives(inc.d_throughput, n, m) if params is not None else None,
        hit_index=hit_index,
        hits=hits,
        sanitized=inc.sanitized,
    )


def draw_batch(problem: Problem, n: int, m: int, seed: int, derivatives: bool,
               camera_fraction: float = 0.0) -> ResidualBatch:
    """Sample ``n`` residual points and ``m`` incident samples each; with ``derivatives``, also
    the forward-mode derivatives w.r.t. every optimized scalar (for the differential residual)."""
    return evaluate_batch(problem, draw_geometry(problem, n, m, seed, camera_fraction), derivatives)


def incident_radiance(batch: ResidualBatch, field: NeuralField | None) -> torch.Tensor:
    """``L_r(x')`` of every incident sample, ``(N, M, channels)``; zeros without a field."""
    n, m = batch.shape
    if field is None:
        return torch.zeros(n, m, 3)
    out = torch.zeros(n * m, field.channels)
    out[batch.hit_index] = field(batch.hits)
    return out.reshape(n, m, field.channels)


def radiance_rhs(batch: ResidualBatch, radiance: NeuralField | None, l_hit: torch.Tensor | None = None) -> torch.Tensor:
    """Right-hand side of Eq. 5, ``(N, 3)``: ``mean_M[emitted + throughput · L_phi(x')]``.
    ``l_hit``: ``incident_radiance(batch, radiance)`` when the caller already has it."""
    return radiance_rhs_samples(batch, radiance, l_hit).mean(1)


def radiance_rhs_samples(batch: ResidualBatch, radiance: NeuralField | None,
                       l_hit: torch.Tensor | None = None) -> torch.Tensor:
    """The ``M`` terms of :func:`radiance_rhs` before their mean, ``(N, M, 3)``."""
    if l_hit is None:
        l_hit = incident_radiance(batch, radiance)
    return batch.emitted + batch.throughput * l_hit


def differential_rhs(batch: ResidualBatch, radiance: NeuralField | None, differential: NeuralField | None,
                     layout: DerivativeLayout, l_hit: torch.Tensor | None = None,
                     dl_hit: torch.Tensor | None = None) -> torch.Tensor:
    """Right-hand side of Eq. 6 for the active scalars, ``(N, A, 3)``.

    ``mean_M[∂emitted + ∂throughput · L_phi(x') + throughput · dL_theta(x')]``; a missing field
    or term contributes zero (``radiance=None``: direct illumination only; ``differential=None``:
    the radiance-cache approximation ``∂L_r(x') = 0``; no ``∂throughput``: no BSDF parameter).
    ``l_hit`` ``(N, M, 3)`` / ``dl_hit`` ``(N, M, K)``: the fields at ``x'`` when the caller already
    has them (a step that trains both fields on one batch evaluates them once).
    """
    return differential_rhs_samples(batch, radiance, differential, layout, l_hit, dl_hit).mean(1)


def differential_rhs_samples(batch: ResidualBatch, radiance: NeuralField | None, differential: NeuralField | None,
                             layout: DerivativeLayout, l_hit: torch.Tensor | None = None,
                             dl_hit: torch.Tensor | None = None) -> torch.Tensor:
    """The ``M`` terms of :func:`differential_rhs` before their mean, ``(N, M, A, 3)``."""
    if batch.d_emitted is None:
        raise ValueError("the batch was drawn without derivatives; use draw_batch(..., derivatives=True)")
    rhs = batch.d_emitted
    if batch.d_throughput is not None and radiance is not None:
        if l_hit is None:
            with torch.no_grad():  # sg(L_phi): the radiance field is a constant of the differential residual
                l_hit = incident_radiance(batch, radiance)
        rhs = rhs + batch.d_throughput * l_hit.detach()[:, :, None, :]
    if differential is not None:
        if dl_hit is None:
            dl_hit = incident_radiance(batch, differential)
        rhs = rhs + batch.throughput[:, :, None, :] * layout.unpack(dl_hit)
    return rhs


def residual_loss(lhs: torch.Tensor, rhs: torch.Tensor, weight: torch.Tensor, scale: torch.Tensor,
                  clip: float | None = None) -> tuple[torch.Tensor, int]:
    """Monte Carlo estimate of ``||r||²`` (Eq. 7, 8) in units of the field's output scale, and the
    number of residual entries beyond ``clip``.

    ``lhs``, ``rhs``: ``(N, C)``; ``weight``: ``(N,)`` = p_ref / p; ``scale``: ``(C,)``. With
    ``clip``, entries with ``|r| > clip`` (fireflies of near-specular lobes and tiny bright lights)
    enter linearly (Huber), so one sample cannot dominate a training step.
    """
    r = (lhs - rhs) / scale
    if clip is None:
        return (weight[:, None] * r.square()).mean(), 0
    a = r.abs()
    quadratic = torch.where(a <= clip, r.square(), 2 * clip * a - clip * clip)
    return (weight[:, None] * quadratic).mean(), int((a > clip).sum())


def debiased_residual(lhs: torch.Tensor, rhs_samples: torch.Tensor, weight: torch.Tensor,
                      scale: torch.Tensor) -> float:
    """Estimate of ``||r||²`` (Eq. 7) of the field itself, without the Monte Carlo noise of its
    right-hand side, in units of the output scale.

    ``E[(lhs - mean_M rhs)²] = (lhs - E rhs)² + Var(rhs) / M``, and the per-point sample variance
    of the ``M`` terms estimates ``Var(rhs)`` without bias, so ``(lhs - rhs)² - s² / M`` estimates
    the residual of the field alone. The noise term dominates the training loss once the field is
    close (it does not fall with training): this is the part that tells whether the field is
    still improving. ``lhs``: ``(N, C)``; ``rhs_samples``: ``(N, M, C)``; ``weight``: ``(N,)``.
    """
    m = rhs_samples.shape[1]
    if m < 2:
        return float("nan")
    r2 = (lhs - rhs_samples.mean(1)).square()
    noise = rhs_samples.var(1) / m
    return float((weight[:, None] * (r2 - noise) / scale.square()).mean())

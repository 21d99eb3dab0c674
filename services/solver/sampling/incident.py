"""The incident integrals of the rendering equation and its derivative, one bounce deep (Eq. 9).

For a surface interaction ``x`` with outgoing direction ``ω_o`` (``si.wi``), the fields represent
*reflected* radiance ``L_r`` and its derivative ``∂L_r``; emission ``E`` and ``∂E`` are added
exactly where a ray meets an emitter. The right-hand sides of Eq. 5 and Eq. 4 become

    L_r(x, ω_o)  = ∫ f(x, ω_i, ω_o) [E(x') + L_r(x')] dω_i⊥
    ∂L_r(x, ω_o) = ∫ f [∂E(x') + ∂L_r(x')] dω_i⊥ + ∫ ∂f [E(x') + L_r(x')] dω_i⊥

where ``x'`` is the first non-delta surface along ``ω_i`` (through mirrors, with throughput
``β``). Each incident sample combines two strategies with the power heuristic:

* emitter sampling (next-event estimation), which can only produce directions towards emitters,
  so its lanes carry ``E`` alone;
* BSDF sampling, whose ray either hits an emitter (``E``, MIS-weighted against emitter sampling
  unless it passed a delta bounce) or a surface of the residual domain, where the fields are
  queried (MIS weight 1: emitter sampling has zero density there).

Everything that does not involve a field is summed here into ``emitted``; what multiplies the
field at ``x'`` is ``throughput``. With ``w``: MIS weight, ``p``: sampling density,

    emitted    = w_e f(ω_e) E(ω_e) / p_e  +  w_b f(ω_b) β E(x') / p_b      (3,)
    throughput = f(ω_b) β / p_b   where x' is a surface, else 0            (3,)

so that ``L_rhs = mean_M(emitted + throughput · L_r(x'))`` and
``∂L_rhs = mean_M(∂emitted + ∂throughput · L_r(x') + throughput · ∂L_r(x'))``. The derivatives
``∂emitted`` and ``∂throughput`` (one per optimized scalar) come from forward-mode AD through
``bsdf.eval`` and ``emitter.eval``; sampling is detached, so pdfs and MIS weights are constants,
as they must be for an unbiased estimate of ``∫ ∂f L``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Protocol

import drjit as dr
import mitsuba as mi

from services.solver.jit_types import Bool, Color, Float, Vector
from services.solver.sampling.delta import trace_through_delta
from services.solver.sampling.surface import queryable


class Tracked(Protocol):
    """What the incident estimator needs of the optimized scalars: forward-mode derivatives of
    its outputs (``services.solver.scene.params.ParameterSet``, whose probe uses this module)."""

    def forward(self, outputs: Sequence, scalars: Sequence[int] | None = None) -> list[list]: ...

#: Densities below this are treated as "cannot sample": the sample contributes nothing instead of
#: an unbounded f / p (near-specular lobes away from their peak, grazing emitter samples).
PDF_FLOOR = 1e-12


def mis_weight(pdf_a, pdf_b):
    """Power heuristic (β = 2) weight of strategy ``a``, as ``1 / (1 + (p_b / p_a)²)``: no overflow
    for the huge densities of near-specular lobes (p² would exceed float32), 0 where ``p_a`` is 0."""
    ratio = safe_div(pdf_b, pdf_a)
    return dr.select(pdf_a > PDF_FLOOR, dr.rcp(1.0 + dr.square(ratio)), 0.0)


def safe_div(a, b):
    """``a / b`` where ``b`` is a usable density, else 0."""
    return dr.select(b > PDF_FLOOR, a / b, 0.0)


@dataclass
class IncidentSamples:
    """Dr.Jit lanes of one incident sample each (``K`` lanes; ``K = B·M`` for residuals).

    emitted, throughput      mi.Color3f (K)
    d_emitted, d_throughput  one mi.Color3f (K) per differentiated scalar (empty when not
                             requested; ``d_throughput`` is None when ∂f is not attached)
    hit                      interaction at ``x'`` (query the fields where ``hit_surface``)
    hit_surface              mi.Bool (K)
    sanitized                number of lanes whose non-finite values were zeroed
    """

    emitted: Color
    throughput: Color
    d_emitted: list
    d_throughput: list | None
    hit: mi.SurfaceInteraction3f
    hit_surface: Bool
    sanitized: int = 0


def _finite(value: Color) -> Bool:
    return dr.all(dr.isfinite(value))


@dataclass
class IncidentGeometry:
    """What one MIS incident sample per lane depends on besides the BSDF and emitter *values*:
    the sampled directions, their densities and MIS weights, and what the rays hit (``K`` lanes,
    detached). Geometry is fixed in every job, so a geometry stays valid when BSDF or emitter
    parameters change: the densities it was sampled with remain valid importance weights (and the
    two MIS weights of a direction still sum to one), so re-evaluating ``f`` and ``E`` on it
    (:func:`evaluate_incident`) is an unbiased estimate of Eq. 9 for the new parameters. Its
    variance grows if the BSDF moves far from the one it was sampled with (a pool refreshes it).

    si            x, with ω_o = ``si.wi``                active       lanes with a valid x
    ds, wo_e      emitter sample (world / local)         active_e     emitter sample usable
    w_e           its MIS weight
    wo_b, pdf_b   BSDF sample (local) and its density    active_b     BSDF sample usable
    delta_b       the sampled lobe is ideal-specular     delta_weight its detached sample weight
    beta          throughput of the delta chain after x (``mi.Spectrum``)
    hit           x', the first non-delta hit along ω_b  hits_emitter / hit_surface
    w_b           MIS weight of an emitter hit by the BSDF sample
    """

    si: mi.SurfaceInteraction3f
    active: Bool
    ds: mi.DirectionSample3f
    active_e: Bool
    wo_e: Vector
    w_e: Float
    wo_b: Vector
    pdf_b: Float
    active_b: Bool
    delta_b: Bool
    delta_weight: Color
    beta: Color
    hit: mi.SurfaceInteraction3f
    hits_emitter: Bool
    w_b: Float
    hit_surface: Bool

    def schedule(self) -> None:
        """Materialise every lane (so that later evaluations do not re-trace the sampling)."""
        dr.eval(self.si, self.active, self.ds, self.active_e, self.wo_e, self.w_e, self.wo_b, self.pdf_b,
                self.active_b, self.delta_b, self.delta_weight, self.beta, self.hit, self.hits_emitter, self.w_b,
                self.hit_surface)


def sample_geometry(scene: mi.Scene, si: mi.SurfaceInteraction3f, sampler: mi.Sampler, *, delta_depth: int,
                    active: Bool = True) -> IncidentGeometry:
    """Draw one emitter sample and one BSDF sample per lane of ``si`` (detached) and trace the
    BSDF ray through delta surfaces to ``x'``. Nothing here is differentiated."""
    active = mi.Bool(active) & si.is_valid()
    ctx = mi.BSDFContext()
    bsdf = si.bsdf()

    # ----------------------- Emitter sampling (detached) -----------------------
    with dr.suspend_grad():
        ds, _ = scene.sample_emitter_direction(si, sampler.next_2d(active), True, active)
        active_e = active & (ds.pdf > 0)
        wo_e = si.to_local(ds.d)
        pdf_bsdf_e = bsdf.pdf(ctx, si, wo_e, active_e)
        w_e = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, pdf_bsdf_e))
        u1, u2 = sampler.next_1d(active), sampler.next_2d(active)

    # --------------------------- BSDF sampling (detached) ---------------------------
    with dr.suspend_grad():
        bs, bs_weight = bsdf.sample(ctx, si, u1, u2, active)
        active_b = active & (bs.pdf > 0)
        delta_b = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        ray = si.spawn_ray(si.to_world(bs.wo))
        chain = trace_through_delta(scene, ray, sampler, delta_depth, active_b)
        hit = chain.si
        emitter = hit.emitter(scene, chain.active)
        hits_emitter = chain.active & (emitter != None)
        ds_hit = mi.DirectionSample3f(scene, hit, si)
        direct = hits_emitter & ~delta_b & ~chain.passed
        pdf_em_hit = scene.pdf_emitter_direction(si, ds_hit, direct)
        w_b = dr.select(direct, mis_weight(bs.pdf, pdf_em_hit), 1.0)
        hit_surface = chain.active & queryable(hit, scene)
    return IncidentGeometry(si, active, ds, active_e, wo_e, w_e, bs.wo, bs.pdf, active_b, delta_b,
                            mi.Spectrum(bs_weight), chain.beta, hit, hits_emitter, w_b, hit_surface)


def _evaluate(scene, g: IncidentGeometry, attach_bsdf: bool = True, attach_emission: bool = True):
    """Evaluate ``emitted`` and ``throughput`` (attached) on sampled geometry.

    A sampled delta lobe (the coating of a plastic, say) contributes its detached sample weight:
    like Mitsuba's ``prb`` (detached sampling), no derivative flows through ideal-specular weights.
    ``attach_bsdf`` / ``attach_emission`` off: that factor is evaluated detached (`choose_effects`
    found its derivative zero, or the job forced the term off).
    """
    maybe_bsdf = (lambda x: x) if attach_bsdf else dr.detach
    maybe_emission = (lambda x: x) if attach_emission else dr.detach
    ctx = mi.BSDFContext()
    si, hit = g.si, g.hit
    bsdf = si.bsdf()
    with dr.suspend_grad():
        emitter = hit.emitter(scene, g.hits_emitter)

    # ------------------- Attached evaluation of f and E ------------------------
    # Evaluated (not symbolic) virtual calls: with symbolic calls, Dr.Jit 1.5 cannot forward-
    # propagate from one parameter into two calls that both read it implicitly (bsdf.eval at
    # ω_e and at ω_b): "edge ... lies outside of the current dr.isolate_grad() scope".
    with dr.resume_grad(), dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
        f_e = maybe_bsdf(bsdf.eval(ctx, si, g.wo_e, g.active_e))
        le_e = maybe_emission(scene.eval_emitter_direction(si, g.ds, g.active_e))
        from_emitter = dr.select(g.active_e, g.w_e * f_e * safe_div(le_e, g.ds.pdf), 0.0)

        f_b = maybe_bsdf(bsdf.eval(ctx, si, g.wo_b, g.active_b & ~g.delta_b))
        f_over_p = dr.select(g.delta_b, g.delta_weight, safe_div(f_b, g.pdf_b))
        beta = dr.select(g.active_b, f_over_p * g.beta, 0.0)
        le_b = maybe_emission(emitter.eval(hit, g.hits_emitter))
        emitted = from_emitter + dr.select(g.hits_emitter, g.w_b * beta * le_b, 0.0)
        throughput = dr.select(g.hit_surface, beta, 0.0)
    return emitted, throughput


def evaluate_attached(scene: mi.Scene, geometry: IncidentGeometry, *, attach_bsdf: bool = True,
                      attach_emission: bool = True) -> tuple[Color, Color]:
    """``emitted`` and ``throughput`` on ``geometry`` with their AD edges kept (under
    ``ParameterSet.tracking``): what a caller differentiates in reverse mode itself (the
    many-parameter head's ``dz/dp``, ``services.solver.estimators.methods.head``). Non-finite
    lanes are not zeroed here; the caller guards them."""
    return _evaluate(scene, geometry, attach_bsdf, attach_emission)


def sample_incident(scene: mi.Scene, si: mi.SurfaceInteraction3f, sampler: mi.Sampler, *,
                    delta_depth: int, parameters: Tracked | None = None, scalars=None,
                    attach_bsdf: bool = True, attach_emission: bool = True,
                    active: Bool = True) -> IncidentSamples:
    """One emitter sample and one BSDF sample per lane of ``si`` (Eq. 9 with MIS).

    When ``parameters`` is given, the caller has enabled tracking on them
    (``ParameterSet.tracking``) and the derivatives of ``emitted`` and ``throughput`` with
    respect to every optimized scalar (or the ``scalars`` listed) are returned too.
    ``∂throughput`` is ``None`` without ``attach_bsdf``: only ``∂f`` makes it non-zero.
    """
    geometry = sample_geometry(scene, si, sampler, delta_depth=delta_depth, active=active)
    return evaluate_incident(scene, geometry, parameters=parameters, scalars=scalars, attach_bsdf=attach_bsdf,
                             attach_emission=attach_emission)


def evaluate_incident(scene: mi.Scene, geometry: IncidentGeometry, *, parameters: Tracked | None = None,
                      scalars=None, attach_bsdf: bool = True, attach_emission: bool = True) -> IncidentSamples:
    """``emitted``, ``throughput`` and (with ``parameters``, under ``ParameterSet.tracking``)
    their forward-mode derivatives on already sampled ``geometry``: the BSDF and emitter values of
    Eq. 9 for the scene's current parameters. :func:`sample_incident` is
    ``evaluate_incident(sample_geometry(...))``; a pool calls it again after a parameter step."""
    emitted, throughput = _evaluate(scene, geometry, attach_bsdf, attach_emission)
    hit, hit_surface = geometry.hit, geometry.hit_surface
    d_emitted: list[Color] = []
    d_throughput: list[Color] | None = [] if attach_bsdf else None
    if parameters is not None:
        outputs = [emitted, throughput] if attach_bsdf else [emitted]
        for grads in parameters.forward(outputs, scalars):
            d_emitted.append(grads[0])
            if d_throughput is not None:
                d_throughput.append(grads[1])

    emitted, throughput = dr.detach(emitted), dr.detach(throughput)
    # Guard: a NaN/Inf lane (grazing angles, degenerate pdfs) is zeroed and counted, never trained on.
    ok = _finite(emitted) & _finite(throughput)
    for d in d_emitted + (d_throughput or []):
        ok &= _finite(d)
    bad: Vector = dr.count(~ok)
    sanitized = int(bad[0]) if dr.width(ok) else 0
    if sanitized:
        emitted = dr.select(ok, emitted, 0.0)
        throughput = dr.select(ok, throughput, 0.0)
        d_emitted = [dr.select(ok, d, 0.0) for d in d_emitted]
        d_throughput = None if d_throughput is None else [dr.select(ok, d, 0.0) for d in d_throughput]
        hit_surface = hit_surface & ok  # not in place: the geometry may be evaluated again
    return IncidentSamples(emitted, throughput, d_emitted, d_throughput, hit, hit_surface, sanitized)

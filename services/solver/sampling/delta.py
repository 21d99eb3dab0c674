"""Rays through ideal-specular (delta) surfaces.

Mirrors and smooth glass are never residual points and carry no field. A ray that hits one is
continued by sampling the delta BSDF (a deterministic reflection, or a Fresnel-weighted choice
between reflection and refraction) until it reaches a surface with a smooth lobe, an emitter,
or escapes; the product of the sample weights is the chain's throughput ``β``. Lanes still on a
delta surface after ``max_depth`` bounces are dropped (their contribution is cut, as a path
tracer with that maximum depth would).

Sampling is detached, as in Mitsuba's ``prb``: properties of ideal-specular BSDFs (a mirror's
reflectance, a glass's IOR) receive no derivative, and :class:`services.solver.scene.params.ParameterSet`
refuses to optimize them rather than return a silent zero.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from services.solver.jit_types import Bool, Color
from services.solver.sampling.surface import pure_delta


@dataclass
class DeltaChain:
    """End of a ray after its delta bounces.

    si      first non-delta interaction (invalid when the ray escaped)
    beta    throughput of the delta bounces (``mi.Spectrum``, 1 when there were none; detached)
    passed  whether at least one delta bounce happened (emitter sampling could not have
            produced such a path, so an emitter found there gets MIS weight 1)
    active  lanes that ended within the depth budget
    """

    si: mi.SurfaceInteraction3f
    beta: Color
    passed: Bool
    active: Bool


def trace_through_delta(scene: mi.Scene, ray: mi.Ray3f, sampler: mi.Sampler, max_depth: int,
                        active: Bool) -> DeltaChain:
    ctx = mi.BSDFContext()
    with dr.suspend_grad():
        si = scene.ray_intersect(ray, active)
    beta = mi.Spectrum(1.0)
    passed = mi.Bool(False)
    on_delta = active & si.is_valid() & pure_delta(si.bsdf().flags())
    for _ in range(max_depth):
        if not dr.any(on_delta):
            break
        bsdf = si.bsdf()
        u1, u2 = sampler.next_1d(on_delta), sampler.next_2d(on_delta)
        with dr.suspend_grad():
            bs, weight = bsdf.sample(ctx, si, u1, u2, on_delta)
            beta[on_delta] = beta * weight
            next_ray = si.spawn_ray(si.to_world(bs.wo))
            si_next = scene.ray_intersect(next_ray, on_delta)
            si[on_delta] = si_next
            passed |= on_delta
            on_delta &= si.is_valid() & pure_delta(si.bsdf().flags())
            # Materialise the loop state, the sampler's included: otherwise every bounce re-traces
            # all previous ones (quadratic work, and a new, larger kernel to compile at each depth).
            sampler.schedule_state()
            dr.eval(si, beta, passed, on_delta)
    return DeltaChain(si, beta, passed, active & ~on_delta)

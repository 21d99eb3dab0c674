"""The camera-hit methods: ``ndrf-lhs``, ``ndrf-rhs``, ``radiance-cache`` and ``direct``.

All four trace the camera's primary rays (through delta surfaces) to their first non-delta hit
``x``, reached with delta throughput ``β``, and estimate there (Eq. 3, 11)

    dI = β · [∂E(x) + ∂L_r(x)]

where ``∂E(x)`` is exact (forward-mode AD of ``emitter.eval``) and ``∂L_r(x)`` is what the method
estimates:

=================  ==========================================================================
``ndrf-lhs``       ``dL_theta(x, ω_o)`` (Eq. 11)
``ndrf-rhs``       one MIS bounce from ``x``: the right-hand side of Eq. 4 with ``L_phi`` and
                   ``dL_theta`` at the next hit ``x'`` (Sec. 6.3)
``radiance-cache`` the same bounce with ``L_phi`` but ``∂L_r(x') = 0`` (Sec. 7.1: misses indirect
                   gradients)
``direct``         the same bounce with emitters only: direct illumination, no field
=================  ==========================================================================

Sampling is detached; ``β`` carries no derivative (see ``services.solver.sampling.delta``).

``dz/dp`` (Eq. 10) of a job with a bitmap texture, for ``direct`` and ``radiance-cache``: one
reverse-mode pass per spp-pass (:meth:`OneBounce.adjoint_gradient`), never P images. With per-ray
weights ``w = dz/dy[pixel] · W β / spp`` (detached; a box filter: a pixel is the mean of its rays)

    dz/dp = ∂/∂p Σ_rays w · [E(x) + emitted + throughput · L_phi(x')]

the estimate whose forward-mode derivative the scalar path contracts ray by ray (``L_phi``
detached, absent for ``direct``): the same rays, the same value. The texture's value reaches
``bsdf.eval`` through ``params.update()`` under ``ParameterSet.tracking``, so the backward pass
reaches its ``data``. Jobs without a texture keep the forward-mode contraction.
"""

from __future__ import annotations

import logging
from abc import abstractmethod
from dataclasses import dataclass, replace

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from schemas.methods import Method
from services.solver.estimators.methods.base import DIFFERENTIAL, RADIANCE, Fields, GradientMethod
from services.solver.estimators.methods.head import color
from services.solver.estimators.problem import Problem
from services.solver.fields.field import evaluate
from services.solver.jit_types import Bool, Color, MitsubaObject
from services.solver.sampling.camera import CameraSamples, develop, sample_camera
from services.solver.sampling.incident import IncidentGeometry, evaluate_attached, sample_geometry, sample_incident
from services.solver.sampling.passes import passes_for
from services.solver.sampling.surface import queryable
from services.solver.sampling.tensors import field_query, mask, rgb, to_device, to_host
from services.solver.seeds import derive_seed

log = logging.getLogger(__name__)

#: Camera rays per pass: each holds an incident sample and the derivatives of A scalars.
RAYS_PER_PASS = 1 << 18


class CameraHitMethod(GradientMethod):
    """Shared camera pass: primary rays, delta chains, exact ``∂E`` at emitter hits, then
    :meth:`differential_radiance` at surface hits. Only the active scalars of the problem's layout
    are differentiated; the others get zeros."""

    @abstractmethod
    def differential_radiance(self, problem: Problem, fields: Fields, si: mi.SurfaceInteraction3f,
                              where: mi.Bool, sampler: mi.Sampler) -> torch.Tensor:
        """``∂L_r(x, ω_o)`` at the lanes ``where`` of ``si``: ``(K, A, 3)`` (zeros elsewhere)."""

    # ------------------------------------------------------------ entry points

    def images(self, problem, fields, *, spp, seed, sensor=0):
        self.check(fields)
        width, height = problem.scene.resolution(sensor)
        if problem.layout.active == 0:
            return np.zeros((problem.parameters.n, height, width, 3), np.float32)
        sensor_obj = problem.scene.sensor(sensor)
        passes, per_pass = passes_for(width * height, spp, RAYS_PER_PASS)
        total = np.zeros((problem.layout.active, height, width, 3))
        for k in range(passes):
            samples, values = self._rays(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            total += to_host(develop(sensor_obj, samples, values))
        return problem.layout.scatter_images((total / passes).astype(np.float32), problem.parameters.n)

    def loss_gradient(self, problem, fields, dz_dy, *, spp, seed, sensor=0):
        """Eq. 10 per camera ray: with a box filter a pixel is the mean of its rays, so
        ``dz/dp = Σ_rays dz/dy[pixel(ray)] · dI_ray / spp`` (no per-scalar image is formed)."""
        self.check(fields)
        width, height = problem.scene.resolution(sensor)
        if dz_dy.shape != (height, width, 3):
            raise ValueError(f"dz/dy has shape {dz_dy.shape}, the film is {(height, width, 3)}")
        sensor_obj = problem.scene.sensor(sensor)
        if problem.layout.active == 0:
            return np.zeros(problem.parameters.n)
        if not sensor_obj.film().rfilter().is_box_filter():
            return super().loss_gradient(problem, fields, dz_dy, spp=spp, seed=seed, sensor=sensor)
        passes, per_pass = passes_for(width * height, spp, RAYS_PER_PASS)
        pixel_weights = to_device(dz_dy.reshape(-1, 3), torch.float64)
        active = np.zeros(problem.layout.active)
        for k in range(passes):
            _, values = self._rays(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            rays = values.double().reshape(width * height, per_pass, -1, 3)
            active += to_host(torch.einsum("xsac,xc->a", rays, pixel_weights)) / per_pass
        out = np.zeros(problem.parameters.n)
        out[list(problem.layout.scalars)] = active / passes
        return out

    # ------------------------------------------------------------ camera pass

    @staticmethod
    def _camera_hits(problem: Problem, sensor: mi.Sensor, spp: int, seed: int):
        """The camera rays of one pass and where they land: ``(samples, sampler, emitter,
        on_emitter, on_surface)``, detached; the same seed draws the same rays."""
        scene = problem.scene.scene
        samples, sampler = sample_camera(scene, sensor, spp, seed, problem.delta_depth)
        si, active = samples.chain.si, samples.chain.active
        with dr.suspend_grad():
            emitter = si.emitter(scene, active)
            on_emitter = active & (emitter != None)
            on_surface = active & queryable(si, scene)
        return samples, sampler, emitter, on_emitter, on_surface

    def _rays(self, problem: Problem, fields: Fields, sensor: mi.Sensor, spp: int,
              seed: int) -> tuple[CameraSamples, torch.Tensor]:
        """The per-ray derivatives ``dI`` of one pass: ``(K, A, 3)``, ``K = W·H·spp`` in Mitsuba's
        pixel-major order."""
        params, layout = problem.parameters, problem.layout
        samples, sampler, emitter, on_emitter, on_surface = self._camera_hits(problem, sensor, spp, seed)
        chain, si = samples.chain, samples.chain.si
        d_reflected = self.differential_radiance(problem, fields, si, on_surface, sampler)  # (K, A, 3)
        if problem.attach_emission:  # ∂E at camera hits on emitters (exact)
            with params.tracking():
                with dr.resume_grad(), dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
                    emitted = dr.select(on_emitter, emitter.eval(si, on_emitter), 0.0)
                d_emitted = torch.stack([rgb(g[0]) for g in params.forward([emitted], layout.scalars)], 1)
            d_reflected = d_reflected + d_emitted
        scale = rgb(samples.weight * chain.beta)[:, None, :]                                   # (K, 1, 3)
        return samples, scale * d_reflected


class NdrfLhs(CameraHitMethod):
    """``∂L_r(x) = dL_theta(x, ω_o)`` at the camera hit (Eq. 11).

    From a plan without ``dL_theta`` (no interreflection: one bounce with emission is exact, or the
    field forced off) it becomes that one-bounce estimate."""

    name = Method.NDRF_LHS
    uses = frozenset({RADIANCE, DIFFERENTIAL})

    def __init__(self, *, radiance: bool = False, differential: bool = True):
        super().__init__(radiance=radiance, differential=differential)

    @classmethod
    def from_plan(cls, plan, depth):
        if plan is not None and not plan.differential_field.value:
            return OneBounce(cls.name, radiance=bool(plan.radiance_field.value), differential=False)
        return cls()

    def differential_radiance(self, problem, fields, si, where, sampler):
        with torch.no_grad():
            return problem.layout.unpack(evaluate(fields.differential, field_query(si), mask(where)))


class OneBounce(CameraHitMethod):
    """``∂L_r(x)`` by one MIS bounce from the camera hit: the right-hand side of Eq. 4 (Eq. 9 with
    ``M = 1`` per camera ray) with the incident radiance ``L_phi`` and differential radiance
    ``dL_theta`` at ``x'`` where the method uses them, zero where it does not (radiance cache:
    ``dL = 0``; direct: both zero)."""

    uses = frozenset({RADIANCE, DIFFERENTIAL})

    def __init__(self, name: Method, *, radiance: bool, differential: bool):
        self.name = name  # type: ignore[misc]  # the public method this instance realises
        super().__init__(radiance=radiance, differential=differential)

    def differential_radiance(self, problem, fields, si, where, sampler):
        params, layout = problem.parameters, problem.layout
        with params.tracking():
            inc = sample_incident(problem.scene.scene, si, sampler, delta_depth=problem.delta_depth,
                                  parameters=params, scalars=layout.scalars, attach_bsdf=problem.attach_bsdf,
                                  attach_emission=problem.attach_emission, active=where)
        problem.count_sanitized("camera", inc.sanitized)
        out = torch.stack([rgb(g) for g in inc.d_emitted], 1)                 # (K, A, 3)
        with torch.no_grad():
            hit_surface = mask(inc.hit_surface)
            hits = field_query(inc.hit)
            if self.needs_radiance and inc.d_throughput is not None:
                d_throughput = torch.stack([rgb(g) for g in inc.d_throughput], 1)
                out = out + d_throughput * evaluate(fields.radiance, hits, hit_surface)[:, None, :]
            if self.needs_differential:
                dl = layout.unpack(evaluate(fields.differential, hits, hit_surface))
                out = out + rgb(inc.throughput)[:, None, :] * dl
        return out

    # ------------------------------------------------------------ textures: one adjoint pass

    def loss_gradient(self, problem, fields, dz_dy, *, spp, seed, sensor=0):
        """A job with a texture: :meth:`adjoint_gradient` (module docstring); otherwise the
        forward-mode contraction per ray (:meth:`CameraHitMethod.loss_gradient`)."""
        if problem.parameters.has_textures and not self.needs_differential:
            return self.adjoint_gradient(problem, fields, dz_dy, spp=spp, seed=seed, sensor=sensor)
        return super().loss_gradient(problem, fields, dz_dy, spp=spp, seed=seed, sensor=sensor)

    def adjoint_gradient(self, problem: Problem, fields: Fields, dz_dy: np.ndarray, *, spp: int, seed: int,
                         sensor: int = 0) -> np.ndarray:
        """``dz/dp`` ``(P,)`` by one Dr.Jit backward pass per spp-pass over the rays (and samples)
        of :meth:`images`: whatever ``P``, never a per-scalar derivative. Scalars outside the
        problem's layout get zeros, as on the forward-mode path."""
        self.check(fields)
        if self.needs_differential:
            raise ValueError(f"{self.name} with dL_theta has no adjoint pass (its field has an output per scalar)")
        width, height = problem.scene.resolution(sensor)
        if dz_dy.shape != (height, width, 3):
            raise ValueError(f"dz/dy has shape {dz_dy.shape}, the film is {(height, width, 3)}")
        params, layout = problem.parameters, problem.layout
        if layout.active == 0:
            return np.zeros(params.n)
        sensor_obj = problem.scene.sensor(sensor)
        if not sensor_obj.film().rfilter().is_box_filter():
            raise ValueError(f"{self.name} contracts dz/dy per ray for a texture job: it needs a box pixel filter")
        passes, per_pass = passes_for(width * height, spp, RAYS_PER_PASS)
        pixel = to_device(dz_dy.reshape(-1, 3), torch.float32)
        total = np.zeros(params.n)
        for k in range(passes):
            total += self._adjoint_pass(problem, fields, sensor_obj, pixel, per_pass, passes,
                                        derive_seed(seed, "camera", k))
        if layout.active < params.n:
            kept = np.zeros(params.n)
            kept[list(layout.scalars)] = total[list(layout.scalars)]
            total = kept
        return total

    def _adjoint_pass(self, problem: Problem, fields: Fields, sensor: mi.Sensor, pixel: torch.Tensor, spp: int,
                      passes: int, seed: int) -> np.ndarray:
        """One pass of :meth:`adjoint_gradient`: the samples of :meth:`_rays` (the same seed draws
        the same camera rays and incident samples), the estimate attached, one backward pass:
        ``(P,)``.

        The forward-mode path's guard (``sample_incident``): a ray whose value or derivative is not
        finite contributes nothing and is counted under ``camera``. A reverse pass has no per-ray
        derivative to test, so a backward pass whose active entries are all finite is kept as is
        (only rays with non-finite values are dropped, by ``select``); otherwise the rays whose
        derivative along the active scalars is not finite (one forward-mode traversal) or whose
        weight is not are found, and the pass is redone with them masked out of every evaluation
        (a ``select`` alone would leak ``0 · inf`` into the texels they read)."""
        scene, params, scalars = problem.scene.scene, problem.parameters, list(problem.layout.scalars)
        samples, sampler, emitter, on_emitter, on_surface = self._camera_hits(problem, sensor, spp, seed)
        with dr.suspend_grad():
            geometry = sample_geometry(scene, samples.chain.si, sampler, delta_depth=problem.delta_depth,
                                       active=on_surface)
            geometry.schedule()
        per_ray = rgb(samples.weight * samples.chain.beta) * pixel.repeat_interleave(spp, 0) / (spp * passes)
        weight: Color = color(per_ray)                                                               # (K, 3)
        radiance = None
        if self.needs_radiance:
            assert fields.radiance is not None  # self.check
            with torch.no_grad():
                radiance = color(evaluate(fields.radiance, field_query(geometry.hit), mask(geometry.hit_surface)))
        hits = _CameraHits(samples.chain.si, emitter, on_emitter, geometry, radiance)
        with params.tracking():   # one graph per tracking block: a traversal clears the texture's edges
            value, ok = hits.estimate(problem, mi.Bool(True))
            out = _backward(params, value * weight)
        if not np.all(np.isfinite(out[scalars])):
            with params.tracking(), dr.resume_grad():
                value, ok = hits.estimate(problem, ok)
                derivative = params.forward_units([value], [scalars])[0][0]
            ok &= dr.all(dr.isfinite(derivative)) & dr.all(dr.isfinite(weight))
            with params.tracking():
                value, ok = hits.estimate(problem, ok)
                out = _backward(params, value * weight)
        problem.count_sanitized("camera", int(np.asarray(dr.count(~ok)).reshape(-1)[0]))
        return out


@dataclass
class _CameraHits:
    """What one adjoint pass evaluates attached, ``K`` lanes: the camera hits ``si`` (on an
    emitter where ``on_emitter``), their incident samples ``geometry`` and the detached cache
    ``radiance`` at ``x'`` (``mi.Color3f``; None for ``direct``)."""

    si: MitsubaObject
    emitter: MitsubaObject
    on_emitter: Bool
    geometry: IncidentGeometry
    radiance: Color | None

    def estimate(self, problem: Problem, keep: Bool) -> tuple[Color, Bool]:
        """``E(x) + emitted + throughput · L_phi(x')`` per ray (``E`` on emitters, the rest on
        surfaces: no ray has both), attached (under ``tracking``), ``(K,)`` ``mi.Color3f``,
        evaluated only on the rays ``keep``; zero on the others and where the incident sample's
        values are not finite. Returns it and the rays it kept."""
        g = self.geometry
        masked = replace(g, active_e=g.active_e & keep, active_b=g.active_b & keep,
                         hits_emitter=g.hits_emitter & keep, hit_surface=g.hit_surface & keep)
        emitted, throughput = evaluate_attached(problem.scene.scene, masked, attach_bsdf=problem.attach_bsdf,
                                                attach_emission=problem.attach_emission)
        with dr.resume_grad():
            ok = keep & dr.all(dr.isfinite(dr.detach(emitted))) & dr.all(dr.isfinite(dr.detach(throughput)))
            value = emitted if self.radiance is None else emitted + throughput * self.radiance
            if problem.attach_emission:  # ∂E at camera hits on emitters (exact)
                on_emitter = self.on_emitter & keep
                with dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
                    value = value + dr.select(on_emitter, self.emitter.eval(self.si, on_emitter), 0.0)
            return dr.select(ok, value, 0.0), ok


def _backward(params, weighted) -> np.ndarray:
    """``∂/∂p Σ weighted`` over the lanes and channels of ``weighted`` (attached, under
    ``tracking``), one reverse-mode pass: ``(P,)``; the parameters' gradients cleared after."""
    with dr.resume_grad():
        # no lane may depend on p (a texture only seen after two bounces): dz/dp is then 0
        dr.backward(dr.sum(dr.sum(weighted, axis=None), axis=None), flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    return params.gradient_vector()


class NdrfRhs(OneBounce):
    """One bounce with ``L_phi`` and ``dL_theta`` at ``x'`` (Sec. 6.3)."""

    name = Method.NDRF_RHS

    def __init__(self, *, radiance: bool = True, differential: bool = True):
        super().__init__(Method.NDRF_RHS, radiance=radiance, differential=differential)

    @classmethod
    def from_plan(cls, plan, depth):
        if plan is None:
            return cls()
        return cls(radiance=bool(plan.radiance_field.value), differential=bool(plan.differential_field.value))


class RadianceCache(OneBounce):
    """One bounce with ``L_phi`` at ``x'`` and ``∂L_r(x') = 0`` (Sec. 7.1)."""

    name = Method.RADIANCE_CACHE
    uses = frozenset({RADIANCE})

    def __init__(self, *, radiance: bool = True, differential: bool = False):
        super().__init__(Method.RADIANCE_CACHE, radiance=radiance, differential=differential)

    @classmethod
    def from_plan(cls, plan, depth):
        return cls(radiance=True if plan is None else bool(plan.radiance_field.value))


class Direct(OneBounce):
    """One bounce with emitters only (direct illumination)."""

    name = Method.DIRECT
    uses = frozenset()

    def __init__(self, *, radiance: bool = False, differential: bool = False):
        super().__init__(Method.DIRECT, radiance=radiance, differential=differential)

"""The camera-hit methods: ``ndrf-lhs``, ``ndrf-rhs``, ``radiance-cache`` and ``direct``.

All four trace the camera's primary rays (through delta surfaces) to their first non-delta hit
``x``, reached with delta throughput ``β`` and sensor weight ``W``, and estimate each ray's
radiance and its derivative there (Eq. 3, 11)

    I  = W β [E(x) + L_r(x)]            dI = W β [∂E(x) + ∂L_r(x)]

where ``∂E(x)`` is exact (AD of ``emitter.eval``) and ``L_r``, ``∂L_r`` are what the method
estimates:

=================  ==========================================================================
``ndrf-lhs``       ``∂L_r(x) = dL_theta(x, ω_o)`` (Eq. 11); ``L_r(x) = L_phi(x)``
``ndrf-rhs``       one MIS bounce from ``x``: the right-hand side of Eq. 4 with ``L_phi`` and
                   ``dL_theta`` at the next hit ``x'`` (Sec. 6.3)
``radiance-cache`` the same bounce with ``L_phi`` but ``∂L_r(x') = 0`` (Sec. 7.1: misses indirect
                   gradients)
``direct``         the same bounce with emitters only: direct illumination, no field
=================  ==========================================================================

The bounce (``services.solver.sampling.incident``) gives ``emitted`` and ``throughput`` ``T``, so
that ``L_r(x) = emitted + T · L_phi(x')`` and ``∂L_r(x) = ∂(emitted + T · L_phi(x')) + T ·
dL_theta(x')``. Sampling is detached (``β``, directions, densities and MIS weights carry no
derivative; see ``services.solver.sampling.delta``), and the fields are detached: the estimate
has an *attached* part, a Dr.Jit expression of the optimized parameters (``E(x)``, ``emitted``,
``T · L_phi``), and a *field* part, the ``dL_theta`` term, a derivative the network gives directly.

One estimate, three modes
-------------------------
As Mitsuba's ``prb`` writes its estimator once as ``sample(mode)`` and switches between
``dr.forward_to`` and ``dr.backward_from`` in one place, :meth:`CameraHitMethod.sample` builds the
estimate of one pass of ``K`` camera rays once (:meth:`CameraHitMethod._estimate`) and ``mode``
says what is taken of it (``A``: the problem's active scalars, ``P``: all scalars):

==========================  =======================================================  =========
``dr.ADMode.Primal``        ``I`` per ray                                             ``(K, 1, 3)``
``dr.ADMode.Forward``       ``dI/dp`` per ray and active scalar: forward-mode AD of   ``(K, A, 3)``
                            the attached part, plus the field part
``dr.ADMode.Backward``      ``dz/dp`` (Eq. 10) for per-ray adjoint weights ``δ``:     ``(P,)``
                            one reverse-mode pass of ``Σ δ · I``, plus ``Σ δ ·``
                            field part
==========================  =======================================================  =========

The entry points drive it: :meth:`~CameraHitMethod.images` splats the forward mode into per-scalar
images; :meth:`~CameraHitMethod.loss_gradient` contracts it with ``dz/dy`` ray by ray (a box filter:
a pixel is the mean of its rays), or, for a job with a bitmap texture and no ``dL_theta``, runs
the backward mode (:meth:`~CameraHitMethod.adjoint_gradient`) with ``δ = dz/dy[pixel] · W β /
spp``: one reverse-mode pass per spp-pass, never P images. The texture's value reaches
``bsdf.eval`` through ``params.update()`` under ``ParameterSet.tracking``, so the backward pass
reaches its ``data``. The same seed draws the same rays and incident samples in every mode.
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
from services.solver.estimators.methods.base import DIFFERENTIAL, RADIANCE, Fields, GradientMethod, contract
from services.solver.estimators.problem import Problem
from services.solver.fields.field import evaluate
from services.solver.jit_types import Bool, Color, MitsubaObject
from services.solver.sampling.camera import CameraSamples, develop, sample_camera
from services.solver.sampling.incident import IncidentGeometry, evaluate_attached, sample_geometry
from services.solver.sampling.passes import passes_for
from services.solver.sampling.surface import queryable
from services.solver.sampling.tensors import color, field_query, floats, mask, rgb, to_device, to_host
from services.solver.scene.params import FORWARD_GROUP
from services.solver.seeds import derive_seed

log = logging.getLogger(__name__)

#: Camera rays per pass: each holds an incident sample and the derivatives of A scalars.
RAYS_PER_PASS = 1 << 18


@dataclass
class CameraPass:
    """One pass of ``K`` camera rays, detached: what every mode evaluates.

    samples      the rays, their first non-delta hits ``x`` (``samples.chain.si``) and film positions
    emitter      the emitter at ``x`` where ``on_emitter`` (mi.EmitterPtr, K)
    scale        ``W β`` per ray, ``(K, 3)`` float32
    reflected    the method's ``L_r(x)`` (:class:`AtHit` or :class:`Bounce`)
    """

    samples: CameraSamples
    emitter: MitsubaObject
    on_emitter: Bool
    scale: torch.Tensor
    reflected: AtHit | Bounce


@dataclass
class AtHit:
    """``L_r(x)`` read at the camera hit (``ndrf-lhs``, Eq. 11): ``radiance`` ``L_phi(x)``
    (``mi.Color3f``, K; the primal's only) and ``field`` ``dL_theta(x)`` ``(K, A, 3)`` (the
    derivative modes' only)."""

    radiance: Color | None
    field: torch.Tensor | None

    def attached(self, problem: Problem, keep: Bool) -> tuple[Color, Bool, Color | None]:
        """``L_r(x)`` (no parameter reaches it), the rays kept (``keep``) and no throughput."""
        return (mi.Color3f(0.0) if self.radiance is None else self.radiance), mi.Bool(keep), None

    def field_part(self, ok: Bool, throughput: Color | None) -> torch.Tensor | None:
        """``dL_theta(x)`` ``(K, A, 3)``."""
        return self.field


@dataclass
class Bounce:
    """``L_r(x)`` by one MIS bounce from the camera hit (Eq. 4 and 9 with ``M = 1`` per ray): the
    detached ``geometry`` of the incident sample, ``L_phi(x')`` (``mi.Color3f``, K; None for
    ``direct``) and ``dL_theta(x')`` ``(K, A, 3)`` (None without the differential field)."""

    geometry: IncidentGeometry
    radiance: Color | None
    differential: torch.Tensor | None

    def attached(self, problem: Problem, keep: Bool) -> tuple[Color, Bool, Color | None]:
        """``emitted + T · L_phi(x')`` per ray, attached (under ``tracking``), evaluated only on the
        rays ``keep``; the rays kept whose ``emitted`` and ``T`` are finite; ``T``."""
        g = self.geometry
        masked = replace(g, active_e=g.active_e & keep, active_b=g.active_b & keep,
                         hits_emitter=g.hits_emitter & keep, hit_surface=g.hit_surface & keep)
        emitted, throughput = evaluate_attached(problem.scene.scene, masked, attach_bsdf=problem.attach_bsdf,
                                                attach_emission=problem.attach_emission)
        with dr.resume_grad():
            ok = keep & dr.all(dr.isfinite(dr.detach(emitted))) & dr.all(dr.isfinite(dr.detach(throughput)))
            value = emitted if self.radiance is None else emitted + throughput * self.radiance
        return value, ok, throughput

    def field_part(self, ok: Bool, throughput: Color | None) -> torch.Tensor | None:
        """``T · dL_theta(x')`` ``(K, A, 3)`` on the rays ``ok``."""
        if self.differential is None:
            return None
        return rgb(dr.select(ok, dr.detach(throughput), 0.0))[:, None, :] * self.differential


class CameraHitMethod(GradientMethod):
    """The camera pass and the one estimate of every mode (module docstring). A subclass says how
    it reads ``L_r(x)`` (:meth:`reflected`). Only the active scalars of the problem's layout are
    differentiated; the others get zeros."""

    geometry_refusal = ("the camera-hit estimate (and the differential field dL_theta) differentiates the shading "
                        "at fixed hits: it has no boundary term for moving silhouettes, and the paper's scope is "
                        "BSDF parameters")

    @abstractmethod
    def reflected(self, problem: Problem, fields: Fields, si: mi.SurfaceInteraction3f, where: mi.Bool,
                  sampler: mi.Sampler, primal: bool) -> AtHit | Bounce:
        """What the method's ``L_r(x, ω_o)`` is made of at the lanes ``where`` of ``si`` (detached:
        samples and field values), for the primal (``primal``) or the derivative modes."""

    # ------------------------------------------------------------ entry points

    def gradient_images(self, problem, fields, *, spp, seed, sensor=0):
        """``dI/dp`` ``(P, H, W, 3)``: the forward mode splatted by the sensor's film."""
        self.check(fields)
        width, height = problem.scene.resolution(sensor)
        if problem.layout.active == 0:
            return np.zeros((problem.parameters.n, height, width, 3), np.float32)
        sensor_obj = problem.scene.sensor(sensor)
        passes, per_pass = passes_for(width * height, spp, RAYS_PER_PASS)
        total = np.zeros((problem.layout.active, height, width, 3))
        for k in range(passes):
            p = self.trace(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            total += to_host(develop(sensor_obj, p.samples, self.sample(dr.ADMode.Forward, problem, p)))
        return problem.layout.scatter_images((total / passes).astype(np.float32), problem.parameters.n)

    def loss_gradient(self, problem, fields, dz_dy, *, spp, seed, sensor=0):
        """``dz/dp`` ``(P,)`` (Eq. 10). A job with a texture and no ``dL_theta``: the backward mode
        (:meth:`adjoint_gradient`). Otherwise the forward mode contracted per camera ray: with a box
        filter ``dz/dp = Σ_rays dz/dy[pixel(ray)] · dI_ray / spp`` (no per-scalar image formed)."""
        if problem.parameters.has_textures and not self.needs_differential:
            return self.adjoint_gradient(problem, fields, dz_dy, spp=spp, seed=seed, sensor=sensor)
        self.check(fields)
        width, height = _film(problem, dz_dy, sensor)
        sensor_obj = problem.scene.sensor(sensor)
        if problem.layout.active == 0:
            return np.zeros(problem.parameters.n)
        if not sensor_obj.film().rfilter().is_box_filter():
            return super().loss_gradient(problem, fields, dz_dy, spp=spp, seed=seed, sensor=sensor)
        passes, per_pass = passes_for(width * height, spp, RAYS_PER_PASS)
        pixel_weights = to_device(dz_dy.reshape(-1, 3), torch.float64)
        active = np.zeros(problem.layout.active)
        for k in range(passes):
            p = self.trace(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            rays = self.sample(dr.ADMode.Forward, problem, p).double()
            active += to_host(torch.einsum("xsac,xc->a", rays.reshape(width * height, per_pass, -1, 3),
                                           pixel_weights)) / per_pass
        out = np.zeros(problem.parameters.n)
        out[list(problem.layout.scalars)] = active / passes
        return out

    def candidate_gradient_and_images(self, problem, fields, loss, *, spp, gradient_spp, seed, depth, sensor=0):
        """The candidate, ``z``, ``dz/dp`` ``(P,)`` and the Jacobian ``dI/dp`` ``(P, H, W, 3)`` from
        one camera pass: the Jacobian's rays are the gradient's (one seed), so ``dz/dp`` is the
        Jacobian contracted with ``dz/dy`` (Eq. 10; what :meth:`loss_gradient` computes ray by ray
        with a box filter, and from the images with any other). The base class traces those rays
        twice; for ``ndrf-lhs`` a pass is most of the gradient's cost (a hash-grid lookup and
        ``dL_theta`` at every hit). A texture job without ``dL_theta`` keeps its backward mode."""
        from services.solver.estimators.render import render

        if problem.parameters.has_textures and not self.needs_differential:
            return super().candidate_gradient_and_images(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                         seed=seed, depth=depth, sensor=sensor)
        candidate = render(problem, spp=spp, seed=derive_seed(seed, "candidate"), sensor=sensor, depth=depth)
        z, dz_dy = loss(candidate)
        images = self.gradient_images(problem, fields, spp=gradient_spp, seed=derive_seed(seed, "gradient"),
                                      sensor=sensor)
        return candidate, z, contract(images, dz_dy), images

    def adjoint_gradient(self, problem: Problem, fields: Fields, dz_dy: np.ndarray, *, spp: int, seed: int,
                         sensor: int = 0) -> np.ndarray:
        """``dz/dp`` ``(P,)`` by the backward mode, one pass per spp-pass over the rays (and
        samples) of :meth:`images`: whatever ``P``, never a per-scalar derivative. Scalars outside
        the problem's layout get zeros, as in the forward mode."""
        self.check(fields)
        width, height = _film(problem, dz_dy, sensor)
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
            p = self.trace(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            adjoint = p.scale * pixel.repeat_interleave(per_pass, 0) / (per_pass * passes)          # (K, 3)
            total += to_host(self.sample(dr.ADMode.Backward, problem, p, adjoint))
        if layout.active < params.n:
            kept = np.zeros(params.n)
            kept[list(layout.scalars)] = total[list(layout.scalars)]
            total = kept
        return total

    # ------------------------------------------------------------ the camera pass and its estimate

    def trace(self, problem: Problem, fields: Fields, sensor: mi.Sensor, spp: int, seed: int,
              primal: bool = False) -> CameraPass:
        """The camera rays of one pass, where they land and what the method reads there, detached;
        the same seed draws the same rays and incident samples."""
        scene = problem.scene.scene
        samples, sampler = sample_camera(scene, sensor, spp, seed, problem.delta_depth)
        si, active = samples.chain.si, samples.chain.active
        with dr.suspend_grad():
            emitter = si.emitter(scene, active)
            on_emitter = active & (emitter != None)
            on_surface = active & queryable(si, scene)
        reflected = self.reflected(problem, fields, si, on_surface, sampler, primal)
        return CameraPass(samples, emitter, on_emitter, rgb(samples.weight * samples.chain.beta), reflected)

    def sample(self, mode: dr.ADMode, problem: Problem, p: CameraPass,
               adjoint: torch.Tensor | None = None) -> torch.Tensor:
        """The estimate of the pass ``p`` in ``mode`` (module docstring): ``I`` ``(K, 1, 3)``,
        ``dI/dp`` ``(K, A, 3)`` or, with the per-ray adjoint weights ``adjoint`` ``(K, 3)``, ``dz/dp``
        ``(P,)``, as tensors on the solver's device. A ray whose value or
        derivative is not finite contributes nothing and is counted under ``camera``
        (``Problem.sanitized``)."""
        params, scalars = problem.parameters, list(problem.layout.scalars)
        everything = mi.Bool(True)
        if mode == dr.ADMode.Primal:
            value, ok, _ = self._estimate(problem, p, everything)
            out = p.scale[:, None, :] * rgb(value)[:, None, :]
        elif mode == dr.ADMode.Forward:
            rows = []
            for group in _groups(scalars, params.has_textures):
                with params.tracking():   # a texture's graph takes FORWARD_GROUP traversals at most
                    value, ok, throughput = self._estimate(problem, p, everything)
                    rows += params.forward([value], group)
            derivative = torch.stack([rgb(row[0]) for row in rows], 1)                               # (K, A, 3)
            ok = ok & _lanes(torch.isfinite(derivative).all(2).all(1))
            field = p.reflected.field_part(ok, throughput)
            out = p.scale[:, None, :] * (derivative if field is None else derivative + field)
            out = torch.where(mask(ok)[:, None, None], out, 0.0)
        else:
            assert adjoint is not None, "the backward mode needs the adjoint weights"
            weight: Color = color(adjoint)
            with params.tracking():   # one graph per tracking block: a traversal clears the texture's edges
                value, ok, throughput = self._estimate(problem, p, everything)
                gradient = _backward(params, value * weight)
            if not np.all(np.isfinite(gradient[scalars])):
                ok = self._finite_rays(problem, p, ok, scalars) & dr.all(dr.isfinite(weight))
                with params.tracking():
                    value, ok, throughput = self._estimate(problem, p, ok)
                    gradient = _backward(params, value * weight)
            field = p.reflected.field_part(ok, throughput)
            if field is not None:
                gradient[scalars] += to_host(torch.einsum("kc,kac->a", adjoint.double(), field.double()))
            problem.count_sanitized("camera", _count(~ok))
            return to_device(gradient)
        problem.count_sanitized("camera", _count(~ok))
        return out

    def _estimate(self, problem: Problem, p: CameraPass, keep: Bool) -> tuple[Color, Bool, Color | None]:
        """``E(x) + L_r(x)`` per ray (the attached part of the estimate; ``E`` on the camera hits
        on emitters, ``L_r`` on surfaces: no ray has both), ``(K,)`` ``mi.Color3f``, evaluated only
        on the rays ``keep`` and zero on the others and where it is not finite; the rays kept; the
        bounce's throughput ``T`` (None at the hit). ``E`` is attached when `choose_effects` kept
        emission terms (``Problem.attach_emission``)."""
        reflected, ok, throughput = p.reflected.attached(problem, keep)
        si, on_emitter = p.samples.chain.si, p.on_emitter & keep
        with dr.resume_grad(), dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
            emitted = dr.select(on_emitter, p.emitter.eval(si, on_emitter), 0.0)
            if not problem.attach_emission:
                emitted = dr.detach(emitted)
            return dr.select(ok, emitted + reflected, 0.0), ok, throughput

    def _finite_rays(self, problem: Problem, p: CameraPass, ok: Bool, scalars: list[int]) -> Bool:
        """The rays ``ok`` whose derivative along the active scalars is finite: one forward-mode
        traversal along their sum. What the backward mode needs when its pass was not finite (a
        reverse pass has no per-ray derivative to test, and a ``select`` alone would leak ``0 ·
        inf`` into the texels the bad rays read: they are masked out of the redone pass)."""
        with problem.parameters.tracking(), dr.resume_grad():
            value, ok, _ = self._estimate(problem, p, ok)
            derivative = problem.parameters.forward_units([value], [scalars])[0][0]
        return ok & dr.all(dr.isfinite(derivative))


def _film(problem: Problem, dz_dy: np.ndarray, sensor: int) -> tuple[int, int]:
    width, height = problem.scene.resolution(sensor)
    if dz_dy.shape != (height, width, 3):
        raise ValueError(f"dz/dy has shape {dz_dy.shape}, the film is {(height, width, 3)}")
    return width, height


def _groups(scalars: list[int], texture: bool) -> list[list[int]]:
    """The scalars in forward-mode groups: all at once, or :data:`FORWARD_GROUP` at a time when a
    bitmap texture is read (Dr.Jit 1.5 crashes on a fourth traversal of such a graph)."""
    size = FORWARD_GROUP if texture else max(1, len(scalars))
    return [scalars[i:i + size] for i in range(0, len(scalars), size)]


def _lanes(where: torch.Tensor) -> Bool:
    """``(K,)`` bool tensor -> ``mi.Bool`` (on the device)."""
    return floats(where.to(torch.float32)) > 0.5


def _count(lanes: Bool) -> int:
    return int(np.asarray(dr.count(lanes)).reshape(-1)[0])


def _backward(params, weighted) -> np.ndarray:
    """``∂/∂p Σ weighted`` over the lanes and channels of ``weighted`` (attached, under
    ``tracking``), one reverse-mode pass: ``(P,)``; the parameters' gradients cleared after."""
    with dr.resume_grad():
        # no lane may depend on p (a texture only seen after two bounces): dz/dp is then 0
        dr.backward(dr.sum(dr.sum(weighted, axis=None), axis=None), flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    return params.gradient_vector()


class NdrfLhs(CameraHitMethod):
    """``∂L_r(x) = dL_theta(x, ω_o)`` at the camera hit (Eq. 11); its primal reads ``L_phi(x)``.

    From effects without ``dL_theta`` (no interreflection: one bounce with emission is exact, or the
    field forced off) it becomes that one-bounce estimate."""

    name = Method.NDRF_LHS
    uses = frozenset({RADIANCE, DIFFERENTIAL})

    def __init__(self, *, radiance: bool = False, differential: bool = True):
        super().__init__(radiance=radiance, differential=differential)

    @classmethod
    def from_effects(cls, effects, depth):
        if effects is not None and not effects.differential_field.value:
            return OneBounce(cls.name, radiance=bool(effects.radiance_field.value), differential=False)
        return cls()

    def reflected(self, problem, fields, si, where, sampler, primal):
        if primal and fields.radiance is None:
            raise ValueError(f"{self.name}'s primal reads L_phi at the camera hits: it needs a trained radiance field")
        with torch.no_grad():
            query, lanes = field_query(si), mask(where)
            if primal:
                return AtHit(color(evaluate(fields.radiance, query, lanes)), None)
            return AtHit(None, problem.layout.unpack(evaluate(fields.differential, query, lanes)))


class OneBounce(CameraHitMethod):
    """``∂L_r(x)`` by one MIS bounce from the camera hit: the right-hand side of Eq. 4 (Eq. 9 with
    ``M = 1`` per camera ray) with the incident radiance ``L_phi`` and differential radiance
    ``dL_theta`` at ``x'`` where the method uses them, zero where it does not (radiance cache:
    ``dL = 0``; direct: both zero)."""

    uses = frozenset({RADIANCE, DIFFERENTIAL})

    def __init__(self, name: Method, *, radiance: bool, differential: bool):
        self.name = name  # type: ignore[misc]  # the public method this instance realises
        super().__init__(radiance=radiance, differential=differential)

    def reflected(self, problem, fields, si, where, sampler, primal):
        with dr.suspend_grad():
            geometry = sample_geometry(problem.scene.scene, si, sampler, delta_depth=problem.delta_depth,
                                       active=where)
            geometry.schedule()
        radiance = differential = None
        with torch.no_grad():
            hits, hit_surface = field_query(geometry.hit), mask(geometry.hit_surface)
            if self.needs_radiance:
                radiance = color(evaluate(fields.radiance, hits, hit_surface))
            if self.needs_differential and not primal:
                differential = problem.layout.unpack(evaluate(fields.differential, hits, hit_surface))
        return Bounce(geometry, radiance, differential)


class NdrfRhs(OneBounce):
    """One bounce with ``L_phi`` and ``dL_theta`` at ``x'`` (Sec. 6.3)."""

    name = Method.NDRF_RHS

    def __init__(self, *, radiance: bool = True, differential: bool = True):
        super().__init__(Method.NDRF_RHS, radiance=radiance, differential=differential)

    @classmethod
    def from_effects(cls, effects, depth):
        if effects is None:
            return cls()
        return cls(radiance=bool(effects.radiance_field.value), differential=bool(effects.differential_field.value))


class RadianceCache(OneBounce):
    """One bounce with ``L_phi`` at ``x'`` and ``∂L_r(x') = 0`` (Sec. 7.1)."""

    name = Method.RADIANCE_CACHE
    uses = frozenset({RADIANCE})

    def __init__(self, *, radiance: bool = True, differential: bool = False):
        super().__init__(Method.RADIANCE_CACHE, radiance=radiance, differential=differential)

    @classmethod
    def from_effects(cls, effects, depth):
        return cls(radiance=True if effects is None else bool(effects.radiance_field.value))


class Direct(OneBounce):
    """One bounce with emitters only (direct illumination)."""

    name = Method.DIRECT
    uses = frozenset()

    def __init__(self, *, radiance: bool = False, differential: bool = False):
        super().__init__(Method.DIRECT, radiance=radiance, differential=differential)

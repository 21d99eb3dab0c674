"""Gradient methods: per-scalar gradient images ``dI/dp`` and loss gradients ``dz/dp``.

One interface, five methods (the names are part of the API):

=================  ==========================================================================
``ndrf-lhs``       query ``dL_theta`` at the first non-delta camera hit (Eq. 11)
``ndrf-rhs``       one bounce from the camera hit, ``dL_theta`` and ``L_phi`` at ``x'`` (Sec. 6.3)
``radiance-cache`` the same bounce with ``L_phi`` but ``∂L_r(x') = 0`` (Sec. 7.1: misses indirect
                   gradients)
``direct``         the same bounce with emitters only: direct illumination, no field
``prb``            Mitsuba's Path Replay Backpropagation integrator (the reference)
=================  ==========================================================================

Every method returns gradient images of shape ``(P, H, W, 3)`` (Eq. 3) for one sensor, and
``dz/dp`` of shape ``(P,)`` for an image-space loss gradient ``dz/dy`` of shape ``(H, W, 3)``
(Eq. 10). The NDRF-family methods contract their images with ``dz/dy``; ``prb`` runs one adjoint
(reverse-mode) pass, whose cost does not grow with ``P``.

At a camera sample whose first non-delta hit is ``x`` (reached with delta throughput ``β``):

    dI = β · [∂E(x) + ∂L_r(x)]

where ``∂E(x)`` is exact (forward-mode AD of ``emitter.eval``) and ``∂L_r(x)`` is what the method
estimates. Sampling is detached; ``β`` carries no derivative (see ``services.sampling.delta``).
"""

from __future__ import annotations

import logging
from abc import ABC, abstractmethod
from typing import ClassVar

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from services.estimators.context import Problem
from services.seeds import derive_seed
from services.fields.field import NeuralField, evaluate
from services.sampling.camera import develop, sample_camera
from services.sampling.incident import sample_incident
from services.sampling.surface import queryable
from services.sampling.tensors import field_query, mask, rgb

log = logging.getLogger(__name__)


class Fields:
    """The trained fields a method may use (``None`` when not trained)."""

    def __init__(self, radiance: NeuralField | None = None, differential: NeuralField | None = None):
        self.radiance = radiance
        self.differential = differential


class GradientMethod(ABC):
    """Base class: how ``∂L_r`` at camera hits is obtained.

    ``needs_radiance`` / ``needs_differential`` tell the trainer which fields to train; a method
    called without a field it needs raises instead of returning a silently wrong gradient.
    """

    name: ClassVar[str]
    needs_radiance: ClassVar[bool] = False
    needs_differential: ClassVar[bool] = False

    def check(self, fields: Fields) -> None:
        if self.needs_radiance and fields.radiance is None:
            raise ValueError(f"{self.name} needs a trained radiance field L_phi")
        if self.needs_differential and fields.differential is None:
            raise ValueError(f"{self.name} needs a trained differential field dL_theta")

    @abstractmethod
    def images(self, problem: Problem, fields: Fields, *, spp: int, seed: int, sensor: int = 0) -> np.ndarray:
        """Gradient images ``dI/dp``, ``(P, H, W, 3)`` float32."""

    def loss_gradient(self, problem: Problem, fields: Fields, dz_dy: np.ndarray, *, spp: int, seed: int,
                      sensor: int = 0) -> np.ndarray:
        """``dz/dp = Σ_pixels dz/dy · dy/dp`` (Eq. 10), ``(P,)`` float64."""
        images = self.images(problem, fields, spp=spp, seed=seed, sensor=sensor)
        return contract(images, dz_dy)


def contract(images: np.ndarray, dz_dy: np.ndarray) -> np.ndarray:
    """``(P, H, W, 3) x (H, W, 3) -> (P,)`` in float64."""
    if images.shape[1:] != dz_dy.shape:
        raise ValueError(f"gradient images {images.shape[1:]} and dz/dy {dz_dy.shape} differ in shape")
    return np.einsum("phwc,hwc->p", images.astype(np.float64), dz_dy.astype(np.float64))


# --------------------------------------------------------------------------------------------
# Camera-hit methods (ndrf-lhs, ndrf-rhs, radiance-cache, direct)
# --------------------------------------------------------------------------------------------

class CameraHitMethod(GradientMethod):
    """Shared camera pass: primary rays, delta chains, exact ``∂E`` at emitter hits, then
    :meth:`differential_radiance` at surface hits. Large images are processed in passes of at
    most ``lanes_per_pass`` rays (equal spp per pass, averaged). Only the active scalars of the
    problem's layout are differentiated; the others get zero images."""

    lanes_per_pass: ClassVar[int] = 1 << 18

    @abstractmethod
    def differential_radiance(self, problem: Problem, fields: Fields, si: mi.SurfaceInteraction3f,
                              where: mi.Bool, sampler: mi.Sampler) -> torch.Tensor:
        """``∂L_r(x, ω_o)`` at the lanes ``where`` of ``si``: ``(K, A, 3)`` (zeros elsewhere)."""

    def images(self, problem, fields, *, spp, seed, sensor=0):
        self.check(fields)
        sensor_obj = problem.scene.sensor(sensor)
        width, height = problem.scene.resolution(sensor)
        if problem.layout.active == 0:
            return np.zeros((problem.parameters.n, height, width, 3), np.float32)
        per_pass = max(1, min(spp, self.lanes_per_pass // max(1, width * height)))
        while spp % per_pass:
            per_pass -= 1
        passes = spp // per_pass
        total = None
        for k in range(passes):
            part = self._one_pass(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            total = part if total is None else total + part
        return problem.layout.scatter_images((total / passes).astype(np.float32), problem.parameters.n)

    def _one_pass(self, problem: Problem, fields: Fields, sensor: mi.Sensor, spp: int, seed: int) -> np.ndarray:
        scene = problem.scene.scene
        params, layout = problem.parameters, problem.layout
        samples, sampler = sample_camera(scene, sensor, spp, seed, problem.delta_depth)
        chain = samples.chain
        si = chain.si
        with dr.suspend_grad():
            emitter = si.emitter(scene, chain.active)
            on_emitter = chain.active & (emitter != None)  # noqa: E711
            on_surface = chain.active & queryable(si, scene)
        d_reflected = self.differential_radiance(problem, fields, si, on_surface, sampler)  # (K, A, 3)
        if problem.attach_emission:  # ∂E at camera hits on emitters (exact)
            with params.tracking():
                with dr.resume_grad(), dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
                    emitted = dr.select(on_emitter, emitter.eval(si, on_emitter), 0.0)
                d_emitted = torch.stack([rgb(g[0]) for g in params.forward([emitted], layout.scalars)], 1)
            d_reflected = d_reflected + d_emitted
        scale = rgb(samples.weight * chain.beta)[:, None, :]                                   # (K, 1, 3)
        return develop(sensor, samples, (scale * d_reflected).numpy())


class NdrfLhs(CameraHitMethod):
    """``∂L_r(x) = dL_theta(x, ω_o)`` at the camera hit (Eq. 11)."""

    name = "ndrf-lhs"
    needs_radiance = False
    needs_differential = True

    def differential_radiance(self, problem, fields, si, where, sampler):
        with torch.no_grad():
            return problem.layout.unpack(evaluate(fields.differential, field_query(si), mask(where)))


class OneBounce(CameraHitMethod):
    """``∂L_r(x)`` by one MIS bounce from the camera hit: the right-hand side of Eq. 4 with the
    incident radiance ``L_phi`` and differential radiance ``dL_theta`` at ``x'`` where the method
    uses them, zero where it does not (radiance cache: ``dL = 0``; direct: both zero)."""

    def __init__(self, radiance: bool, differential: bool):
        self.needs_radiance = radiance
        self.needs_differential = differential

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


class NdrfRhs(OneBounce):
    name = "ndrf-rhs"

    def __init__(self, radiance: bool = True, differential: bool = True):
        super().__init__(radiance, differential)


class RadianceCache(OneBounce):
    name = "radiance-cache"

    def __init__(self, radiance: bool = True):
        super().__init__(radiance, False)


class Direct(OneBounce):
    name = "direct"

    def __init__(self):
        super().__init__(False, False)

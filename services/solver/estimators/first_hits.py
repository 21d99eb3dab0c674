"""Camera rays' first hits, traced once per job at fixed pixel samples, and what the fields give
there: the candidate image ``y`` (Eq. 1 with ``L = E + L_phi``) and the ``ndrf-lhs`` loss gradient
``dz/dp`` contracted per ray (Eq. 3, 10, 11).

Geometry is fixed in every job, so a camera ray's first non-delta hit ``x``, its delta throughput
``β`` and its sensor weight do not change between iterations: only ``E(x)``, ``∂E(x)`` and the
fields do. With ``K = W·H·spp`` rays of a sensor (pixel-major, ``spp`` consecutive rays per pixel):

    y_k        = w_k β_k [E(x_k) + L_phi(x_k, ω_o)]                                  (K, 3)
    ∂y_k       = w_k β_k [∂E(x_k) + dL_theta(x_k, ω_o)]                              (K, A, 3)
    dz/dp_a    = Σ_k Σ_c dz/dy[pixel(k), c] · ∂y_k[a, c] / spp                       (Eq. 10)

``L_phi`` holds every bounce, so the field candidate does not truncate paths as a path tracer of
finite depth does; its bias is the field's error (``tests/unit/test_first_hits.py`` measures it against
a deep path tracer). The pixel samples are fixed for the whole job: the loss is the loss of that
image, and a pixel straddling an edge keeps the value of its fixed samples (use a few spp where
edges matter). With a box filter (the usual case) the film average is the mean of a pixel's
rays; other filters go through the sensor's film (:func:`services.solver.sampling.camera.develop`), and
``dz/dp`` then through the per-scalar images.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import drjit as dr
import numpy as np
import torch

from services.solver.estimators.problem import Problem
from services.solver.fields.field import NeuralField, evaluate
from services.solver.fields.query import FieldQuery
from services.solver.jit_types import Bool, Color
from services.solver.sampling.camera import CameraSamples, develop, sample_camera
from services.solver.sampling.surface import queryable
from services.solver.sampling.tensors import field_query, mask, rgb, to_device, to_host
from services.solver.seeds import derive_seed

log = logging.getLogger(__name__)


@dataclass
class CachedView:
    """The fixed camera samples of one sensor.

    samples       CameraSamples (Dr.Jit; K lanes)        scale       (K, 3) w_k β_k
    on_emitter    mi.Bool (K): x is an emitter           surface     (S,) long: lanes where the fields are defined
    query         FieldQuery (S), encoding precomputed   box         box filter: images are per-pixel means
    """

    sensor: int
    width: int
    height: int
    spp: int
    samples: CameraSamples
    on_emitter: Bool
    scale: torch.Tensor
    surface: torch.Tensor
    query: FieldQuery
    box: bool
    emission_at: np.ndarray | None = None
    emission: tuple | None = None


class FirstHitCache:
    """First hits of every sensor in ``sensors`` at ``spp`` fixed samples per pixel."""

    def __init__(self, problem: Problem, sensors: list[int], spp: int, seed: int, fields: list[NeuralField]):
        self.problem = problem
        self.views: dict[int, CachedView] = {s: self._trace(s, spp, derive_seed(seed, "first-hits", s), fields)
                                             for s in sensors}
        log.info("cached first hits: %d sensor(s), %d spp, %d surface hits", len(self.views), spp,
                 sum(len(v.query) for v in self.views.values()))

    def _trace(self, sensor: int, spp: int, seed: int, fields: list[NeuralField]) -> CachedView:
        problem = self.problem
        scene, sensor_obj = problem.scene.scene, problem.scene.sensor(sensor)
        width, height = problem.scene.resolution(sensor)
        samples, _ = sample_camera(scene, sensor_obj, spp, seed, problem.delta_depth)
        chain = samples.chain
        with dr.suspend_grad():
            emitter = chain.si.emitter(scene, chain.active)
            on_emitter = chain.active & (emitter != None)
            on_surface = chain.active & queryable(chain.si, scene)
            scale: Color = samples.weight * chain.beta
            dr.eval(on_emitter, on_surface, scale)
        surface, query = field_query(chain.si).compact(mask(on_surface))
        for field in fields:
            field.precompute(query)
        lanes = width * height * spp
        scale = rgb(scale).expand(lanes, 3).contiguous()  # a literal (pinhole weight, no delta) is one lane wide
        return CachedView(sensor, width, height, spp, samples, on_emitter, scale, surface, query,
                          bool(sensor_obj.film().rfilter().is_box_filter()))

    # ---------------------------------------------------------------- emission

    def _emission(self, view: CachedView) -> tuple[torch.Tensor, torch.Tensor | None]:
        """``E(x)`` ``(K, 3)`` and, when emission is differentiated, ``∂E(x)`` ``(K, A, 3)`` for the
        current parameters (memoised until they change)."""
        problem = self.problem
        values = problem.parameters.values()
        if view.emission is not None and view.emission_at is not None and np.array_equal(values, view.emission_at):
            return view.emission
        si, where = view.samples.chain.si, view.on_emitter
        scene, params = problem.scene.scene, problem.parameters
        d_emitted = None
        if problem.attach_emission and problem.layout.active:
            with params.tracking():
                with dr.resume_grad(), dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
                    emitted = dr.select(where, si.emitter(scene, where).eval(si, where), 0.0)
                d_emitted = torch.stack([rgb(g[0]) for g in params.forward([emitted], problem.layout.scalars)], 1)
            emitted = dr.detach(emitted)
        else:
            with dr.suspend_grad():
                emitted = dr.select(where, si.emitter(scene, where).eval(si, where), 0.0)
        view.emission, view.emission_at = (rgb(emitted), d_emitted), values
        return view.emission

    # --------------------------------------------------------------- outputs

    def _develop(self, view: CachedView, values: torch.Tensor) -> torch.Tensor:
        """Per-ray values ``(K, C, 3)`` -> images ``(C, H, W, 3)`` through the sensor's film (on the
        device)."""
        return develop(self.problem.scene.sensor(view.sensor), view.samples, values)

    def candidate(self, sensor: int, radiance: NeuralField | None) -> np.ndarray:
        """The candidate image ``(H, W, 3)``: ``E + L_phi`` at the cached first hits (Eq. 1)."""
        view = self.views[sensor]
        emitted, _ = self._emission(view)
        value = emitted.expand(view.scale.shape[0], 3).clone()  # E may be one lane wide too
        if radiance is not None and len(view.query):
            with torch.no_grad():
                value[view.surface] += radiance(view.query)
        return to_host(self._develop(view, (view.scale * value)[:, None, :])[0])

    def _derivatives(self, view: CachedView, differential: NeuralField | None) -> torch.Tensor:
        """``∂y_k`` ``(K, A, 3)``: ``w β (∂E + dL_theta)`` at the cached first hits (Eq. 11)."""
        layout = self.problem.layout
        _, d_emitted = self._emission(view)
        out = torch.zeros(view.scale.shape[0], layout.active, 3)
        if d_emitted is not None:
            out += d_emitted  # (K or 1, A, 3): a derivative Dr.Jit found to be zero is one lane wide
        if differential is not None and len(view.query):
            with torch.no_grad():
                out[view.surface] += layout.unpack(evaluate(differential, view.query))
        return view.scale[:, None, :] * out

    def loss_gradient(self, sensor: int, differential: NeuralField | None, dz_dy: np.ndarray) -> np.ndarray:
        """``dz/dp`` ``(P,)`` float64 for the pixel gradient ``dz_dy`` ``(H, W, 3)``, contracted per ray
        (no per-scalar image is formed with a box filter)."""
        view, problem = self.views[sensor], self.problem
        if dz_dy.shape != (view.height, view.width, 3):
            raise ValueError(f"dz/dy has shape {dz_dy.shape}, the film is {(view.height, view.width, 3)}")
        d_y = self._derivatives(view, differential)
        out = np.zeros(problem.parameters.n)
        if not view.box:
            images = self._develop(view, d_y).double()
            out[list(problem.layout.scalars)] = to_host(torch.einsum("ahwc,hwc->a", images,
                                                                     to_device(dz_dy, torch.float64)))
            return out
        per_ray = to_device(dz_dy, torch.float64).reshape(-1, 1, 3)
        per_pixel = d_y.double().reshape(-1, view.spp, d_y.shape[1], 3).sum(1) / view.spp     # (H·W, A, 3)
        out[list(problem.layout.scalars)] = to_host((per_pixel * per_ray).sum((0, 2)))
        return out

    def gradient_images(self, sensor: int, differential: NeuralField | None) -> np.ndarray:
        """Gradient images ``(P, H, W, 3)`` (only for writing them: :meth:`loss_gradient` does not
        need them)."""
        view = self.views[sensor]
        images = to_host(self._develop(view, self._derivatives(view, differential)))
        return self.problem.layout.scatter_images(images, self.problem.parameters.n)

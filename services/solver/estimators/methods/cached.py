"""A method on camera first hits cached once per job (geometry is fixed in every job).

Chosen by the job's ``render`` settings (``schemas.job.RenderSpec``):

``render.candidate = "field"``     the candidate ``y`` is ``E + L_phi`` at the cached first hits
                                   (no path tracing; every bounce, with the field's bias) instead
                                   of a path tracer (``"path"``, the job's path depth)
``render.first_hits = "cached"``   ``ndrf-lhs`` queries ``dL_theta`` at the cached first hits and
                                   contracts ``dz/dy`` per ray (Eq. 10, 11)

The cache (:class:`~services.solver.estimators.first_hits.FirstHitCache`) holds
``render.gradient_spp`` fixed samples per pixel of every sensor with a target. The wrapped
method keeps its own gradient unless it is ``ndrf-lhs`` with cached first hits.
"""

from __future__ import annotations

import logging

import numpy as np

from schemas.methods import Method
from services.solver.estimators.first_hits import FirstHitCache
from services.solver.estimators.methods.base import Fields, GradientMethod, Loss
from services.solver.estimators.methods.camera_hit import NdrfLhs
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import PathDepth

log = logging.getLogger(__name__)


class CachedFirstHits(GradientMethod):
    """``inner`` with its candidate and/or ``ndrf-lhs`` gradient taken at cached first hits."""

    def __init__(self, inner: GradientMethod, cache: FirstHitCache, *, field_candidate: bool, cached_lhs: bool):
        self.name: Method = inner.name  # type: ignore[misc]  # the public method this instance realises
        self.uses = inner.uses  # type: ignore[misc]
        self.inner, self.cache = inner, cache
        self.field_candidate, self.cached_lhs = field_candidate, cached_lhs and isinstance(inner, NdrfLhs)
        self.needs_radiance = inner.needs_radiance or field_candidate
        self.needs_differential = inner.needs_differential
        if cached_lhs and not self.cached_lhs:
            log.warning("render.first_hits='cached' serves ndrf-lhs only; %s computes its own gradient", inner.name)

    def gradient_images(self, problem: Problem, fields: Fields, *, spp: int, seed: int, sensor: int = 0) -> np.ndarray:
        if self.cached_lhs:
            self.check(fields)
            return self.cache.gradient_images(sensor, fields.differential)
        return self.inner.gradient_images(problem, fields, spp=spp, seed=seed, sensor=sensor)

    def loss_gradient(self, problem: Problem, fields: Fields, dz_dy: np.ndarray, *, spp: int, seed: int,
                      sensor: int = 0) -> np.ndarray:
        if self.cached_lhs:
            self.check(fields)
            return self.cache.loss_gradient(sensor, fields.differential, dz_dy)
        return self.inner.loss_gradient(problem, fields, dz_dy, spp=spp, seed=seed, sensor=sensor)

    def candidate_gradient_and_images(self, problem: Problem, fields: Fields, loss: Loss, *, spp: int,
                                      gradient_spp: int, seed: int, depth: PathDepth,
                                      sensor: int = 0) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        if not self.field_candidate and not self.cached_lhs:  # nothing cached serves this method
            return self.inner.candidate_gradient_and_images(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                            seed=seed, depth=depth, sensor=sensor)
        return super().candidate_gradient_and_images(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                     seed=seed, depth=depth, sensor=sensor)

    def candidate_and_gradient(self, problem: Problem, fields: Fields, loss: Loss, *, spp: int, gradient_spp: int,
                               seed: int, depth: PathDepth, sensor: int = 0) -> tuple[np.ndarray, float, np.ndarray]:
        if not self.field_candidate:
            if not self.cached_lhs:
                return self.inner.candidate_and_gradient(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                         seed=seed, depth=depth, sensor=sensor)
            return super().candidate_and_gradient(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                  seed=seed, depth=depth, sensor=sensor)
        self.check(fields)
        candidate = self.cache.candidate(sensor, fields.radiance)
        z, dz_dy = loss(candidate)
        from services.solver.seeds import derive_seed

        return candidate, z, self.loss_gradient(problem, fields, dz_dy, spp=gradient_spp,
                                                seed=derive_seed(seed, "gradient"), sensor=sensor)

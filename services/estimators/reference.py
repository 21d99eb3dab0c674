"""Path tracing with Mitsuba: the primal render of a candidate (Sec. 5, step 2) and the ``prb``
gradient method (Radiative / Path Replay Backpropagation, the reference).

Large sample counts are split into passes of equal spp with different seeds (averaged), which
keeps memory bounded: a 64x64 image at 4096 spp is 16.7 M paths.
"""

from __future__ import annotations

from typing import ClassVar

import drjit as dr
import mitsuba as mi
import numpy as np

from services.estimators.context import Problem
from services.estimators.gradients import Fields, GradientMethod
from services.seeds import derive_seed

#: Paths per pass (W·H·spp) for the Mitsuba integrators.
LANES_PER_PASS = 1 << 21


def passes_for(width: int, height: int, spp: int) -> tuple[int, int]:
    """``(passes, spp_per_pass)`` with ``passes · spp_per_pass == spp``."""
    per_pass = max(1, min(spp, LANES_PER_PASS // max(1, width * height)))
    while spp % per_pass:
        per_pass -= 1
    return spp // per_pass, per_pass


def path_integrator(max_depth: int) -> mi.Integrator:
    return mi.load_dict({"type": "path", "max_depth": max_depth, "rr_depth": max_depth + 1})


def render(problem: Problem, *, spp: int, seed: int, sensor: int = 0, max_depth: int = 12) -> np.ndarray:
    """Non-differentiable candidate image ``y``, ``(H, W, 3)`` float32 (no Russian roulette)."""
    integrator = path_integrator(max_depth)
    width, height = problem.scene.resolution(sensor)
    passes, per_pass = passes_for(width, height, spp)
    total = None
    with dr.suspend_grad():
        for k in range(passes):
            image = mi.render(problem.scene.scene, sensor=sensor, integrator=integrator, spp=per_pass,
                              seed=derive_seed(seed, "path", k))
            part = np.array(image, dtype=np.float64)[..., :3]
            total = part if total is None else total + part
    return (total / passes).astype(np.float32)


class Prb(GradientMethod):
    """Mitsuba's ``prb`` integrator: gradient images by forward mode (one render per scalar),
    ``dz/dp`` by one adjoint render. Russian roulette is off (``rr_depth > max_depth``) so that the
    reference has no roulette noise."""

    name: ClassVar[str] = "prb"

    def __init__(self, max_depth: int = 12):
        if max_depth < 1:
            raise ValueError(f"prb max_depth must be >= 1, got {max_depth}")
        self.max_depth = max_depth
        self.integrator = mi.load_dict({"type": "prb", "max_depth": max_depth, "rr_depth": max_depth + 1})

    def images(self, problem: Problem, fields: Fields, *, spp: int, seed: int, sensor: int = 0) -> np.ndarray:
        params = problem.parameters
        width, height = problem.scene.resolution(sensor)
        passes, per_pass = passes_for(width, height, spp)
        out = np.zeros((params.n, height, width, 3), np.float64)
        with params.tracking():
            for i in range(params.n):
                key, tangent = params.tangent(i)
                for k in range(passes):
                    dr.set_grad(params.params[key], tangent)
                    image = mi.render(problem.scene.scene, params.params, sensor=sensor, integrator=self.integrator,
                                      spp=per_pass, seed=derive_seed(seed, "path", k))
                    dr.forward_to(image)
                    out[i] += np.array(dr.grad(image), dtype=np.float64)[..., :3]
                    dr.clear_grad(params.params[key])
        return (out / passes).astype(np.float32)

    def loss_gradient(self, problem: Problem, fields: Fields, dz_dy: np.ndarray, *, spp: int, seed: int,
                      sensor: int = 0) -> np.ndarray:
        params = problem.parameters
        width, height = problem.scene.resolution(sensor)
        if dz_dy.shape != (height, width, 3):
            raise ValueError(f"dz/dy has shape {dz_dy.shape}, the film is {(height, width, 3)}")
        passes, per_pass = passes_for(width, height, spp)
        total = np.zeros(params.n)
        with params.tracking():
            for k in range(passes):
                image = mi.render(problem.scene.scene, params.params, sensor=sensor, integrator=self.integrator,
                                  spp=per_pass, seed=derive_seed(seed, "path", k))
                # films with an alpha channel render (H, W, 4): the loss only sees RGB
                padded = np.zeros(tuple(image.shape), np.float32)
                padded[..., :3] = dz_dy
                dr.backward(dr.sum(image * mi.TensorXf(padded), axis=None))
                total += np.concatenate([np.asarray(dr.grad(params.params[key]), np.float64).reshape(-1)
                                         for key in params.keys])
                for key in params.keys:
                    dr.clear_grad(params.params[key])
        return total / passes

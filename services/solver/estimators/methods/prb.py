"""``prb``: Mitsuba's Path Replay Backpropagation integrator (Vicini et al. 2021), the reference.

Russian roulette is off (``rr_depth > max_depth``) so that the reference has no roulette noise.
Sampling is detached in ``prb`` as in the camera-hit methods: the same parameters are optimizable.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from schemas.methods import Method
from services.solver.estimators.methods.base import Fields, GradientMethod
from services.solver.estimators.problem import Problem
from services.solver.sampling.passes import passes_for
from services.solver.seeds import derive_seed


class Prb(GradientMethod):
    """``loss_gradient``: one adjoint (reverse-mode) render per pass, whatever the number of
    scalars ``P``; ``images``: one forward-mode render per scalar and pass (only when images are
    written)."""

    name = Method.PRB
    uses = frozenset()

    def __init__(self, *, max_depth: int = 12, radiance: bool = False, differential: bool = False):
        super().__init__(radiance=radiance, differential=differential)
        if max_depth < 1:
            raise ValueError(f"prb max_depth must be >= 1, got {max_depth}")
        self.max_depth = max_depth
        self.integrator = mi.load_dict({"type": "prb", "max_depth": max_depth, "rr_depth": max_depth + 1})

    @classmethod
    def from_plan(cls, plan, max_depth=12):
        return cls(max_depth=max_depth)

    def images(self, problem: Problem, fields: Fields, *, spp: int, seed: int, sensor: int = 0) -> np.ndarray:
        params = problem.parameters
        width, height = problem.scene.resolution(sensor)
        passes, per_pass = passes_for(width * height, spp)
        out = np.zeros((params.n, height, width, 3), np.float64)
        for i in range(params.n):
            key, tangent = params.tangent(i)
            for k in range(passes):
                with params.tracking():  # re-creates the edges from the parameter to what derives from it
                    dr.set_grad(params.params[key], tangent)
                    # Propagate into derived values (a bitmap's texture) before rendering: the render's
                    # own traversal is isolated and would not cross that edge.
                    dr.forward_from(params.params[key], dr.ADFlag.ClearEdges)
                    image = mi.render(problem.scene.scene, params.params, sensor=sensor, integrator=self.integrator,
                                      spp=per_pass, seed=derive_seed(seed, "path", k))
                    dr.forward_to(image)
                    out[i] += np.array(dr.grad(image), dtype=np.float64)[..., :3]
                    dr.clear_grad(params.params[key])
        return (out / passes).astype(np.float32)

    def candidate_and_gradient(self, problem, fields, loss, *, spp, gradient_spp, seed, sensor=0, max_depth=12):
        """One differentiable render, as Mitsuba's own optimization loops do: the primal image is
        the candidate (``spp``), and ``dr.backward`` replays paths with independent samples
        (``seed_grad``, ``gradient_spp``): one primal and one adjoint pass per iteration, whatever
        the number of scalars. Falls back to separate passes when either does not fit one pass."""
        params = problem.parameters
        width, height = problem.scene.resolution(sensor)
        if max(passes_for(width * height, spp)[0], passes_for(width * height, gradient_spp)[0]) > 1:
            return super().candidate_and_gradient(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                  seed=seed, sensor=sensor, max_depth=max_depth)
        with params.tracking():
            image = mi.render(problem.scene.scene, params.params, sensor=sensor, integrator=self.integrator,
                              spp=spp, spp_grad=gradient_spp, seed=derive_seed(seed, "primal"),
                              seed_grad=derive_seed(seed, "adjoint"))
            candidate = np.array(image, dtype=np.float32)[..., :3]
            z, dz_dy = loss(candidate)
            padded = np.zeros(tuple(image.shape), np.float32)
            padded[..., :3] = dz_dy
            dr.backward(dr.sum(image * mi.TensorXf(padded), axis=None))
            dz_dp = np.concatenate([np.asarray(dr.grad(params.params[key]), np.float64).reshape(-1)
                                    for key in params.keys])
            for key in params.keys:
                dr.clear_grad(params.params[key])
        return candidate, z, dz_dp

    def loss_gradient(self, problem: Problem, fields: Fields, dz_dy: np.ndarray, *, spp: int, seed: int,
                      sensor: int = 0) -> np.ndarray:
        params = problem.parameters
        width, height = problem.scene.resolution(sensor)
        if dz_dy.shape != (height, width, 3):
            raise ValueError(f"dz/dy has shape {dz_dy.shape}, the film is {(height, width, 3)}")
        passes, per_pass = passes_for(width * height, spp)
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

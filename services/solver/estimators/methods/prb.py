"""``prb``: Mitsuba's Path Replay Backpropagation integrator (Vicini et al. 2021), the reference.

Paths have the job's :class:`~services.solver.estimators.render.PathDepth`: by default unbounded
with Russian roulette from depth 5, as Mitsuba does (unbiased). Sampling is detached in ``prb`` as
in the camera-hit methods: the same parameters are optimizable.

Three entry points, each one pass per spp-pass over the film:

``candidate_and_gradient``  one differentiable render: its primal is the candidate, one adjoint
                            pass gives ``dz/dp`` whatever ``P`` (what an Adam iteration costs)
``images``                  the Jacobian ``dI/dp`` ``(P, H, W, 3)`` by forward mode, one render per
                            *group* of scalars that change distinct RGB channels (an RGB albedo's
                            three components change one channel each: one render for the three)
``candidate_gradient_and_images``  what a second-order iteration needs: the candidate from a
                            primal render, the Jacobian from independent samples, and ``dz/dp =
                            Σ dz/dy · J`` contracted from them (unbiased, no adjoint pass)
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from schemas.methods import Method
from services.solver.estimators.losses import ImageLoss
from services.solver.estimators.methods.base import Fields, GradientMethod, Loss, contract
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import PathDepth, opaque_seed, render
from services.solver.sampling.passes import passes_for
from services.solver.seeds import derive_seed


def channel_groups(channels: list[tuple[int, ...]]) -> list[list[int]]:
    """Greedy partition of scalars (given the RGB channels each one changes) into groups whose
    channel sets are pairwise disjoint: one forward-mode render measures a whole group, each
    scalar's derivative read from its own channels. Returns lists of indices into ``channels``."""
    groups: list[list[int]] = []
    used: list[set[int]] = []
    for i, chans in enumerate(channels):
        mine = set(chans)
        for group, taken in zip(groups, used):
            if not taken & mine:
                group.append(i)
                taken |= mine
                break
        else:
            groups.append([i])
            used.append(set(mine))
    return groups


class Prb(GradientMethod):
    """``loss_gradient``: one adjoint (reverse-mode) render per pass, whatever the number of
    scalars ``P``; ``images``: one forward-mode render per channel group and pass."""

    name = Method.PRB
    uses = frozenset()

    def __init__(self, *, depth: PathDepth, radiance: bool = False, differential: bool = False):
        super().__init__(radiance=radiance, differential=differential)
        self.depth = depth
        self.integrator = depth.integrator("prb")

    @classmethod
    def from_plan(cls, plan, depth):
        if depth is None:
            raise ValueError("prb traces paths: it needs a PathDepth (services.solver.estimators.render)")
        return cls(depth=depth)

    # ----------------------------------------------------------- Jacobian

    def images(self, problem: Problem, fields: Fields, *, spp: int, seed: int, sensor: int = 0) -> np.ndarray:
        params, layout = problem.parameters, problem.layout
        width, height = problem.scene.resolution(sensor)
        passes, per_pass = passes_for(width * height, spp)
        out = np.zeros((params.n, height, width, 3), np.float64)
        for group in channel_groups(list(layout.channels)):
            scalars = [layout.scalars[a] for a in group]
            for k in range(passes):
                image = self._forward(problem, scalars, sensor, per_pass, derive_seed(seed, "path", k))
                for a, i in zip(group, scalars):
                    chans = list(layout.channels[a])
                    out[i][..., chans] += image[..., chans]
        return (out / passes).astype(np.float32)

    def _forward(self, problem: Problem, scalars: list[int], sensor: int, spp: int, seed: int) -> np.ndarray:
        """``Σ_i dI/dp_i`` over ``scalars`` by one forward-mode render, ``(H, W, 3)`` float64."""
        params = problem.parameters
        tangents = params.tangents(scalars)
        with params.tracking():  # re-creates the edges from the parameters to what derives from them
            values = [params.params[key] for key in tangents]
            for key, tangent in tangents.items():
                dr.set_grad(params.params[key], tangent)
            # Propagate into derived values (a bitmap's texture) before rendering: the render's own
            # traversal is isolated and would not cross that edge.
            dr.enqueue(dr.ADMode.Forward, *values)
            dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)
            image = mi.render(problem.scene.scene, params.params, sensor=sensor, integrator=self.integrator,
                              spp=spp, seed=opaque_seed(seed))
            dr.forward_to(image)
            out = np.array(dr.grad(image), dtype=np.float64)[..., :3]
            for key in tangents:
                dr.clear_grad(params.params[key])
        return out

    def candidate_gradient_and_images(self, problem: Problem, fields: Fields, loss: Loss, *, spp: int,
                                      gradient_spp: int, seed: int, depth: PathDepth,
                                      sensor: int = 0) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        """The candidate (primal ``path`` render, ``spp``), the Jacobian ``J`` (forward mode,
        ``gradient_spp``, independent samples) and ``dz/dp = Σ_pixels dz/dy · J`` (Eq. 10): unbiased
        for ``l2`` because ``y`` and ``J`` share no sample. No adjoint pass."""
        candidate = render(problem, spp=spp, seed=derive_seed(seed, "candidate"), sensor=sensor, depth=depth)
        z, dz_dy = loss(candidate)
        images = self.images(problem, fields, spp=gradient_spp, seed=derive_seed(seed, "jacobian"), sensor=sensor)
        return candidate, z, contract(images, dz_dy), images

    # ----------------------------------------------------------- gradient

    def candidate_and_gradient(self, problem, fields, loss, *, spp, gradient_spp, seed, depth, sensor=0):
        """One differentiable render, as Mitsuba's own optimization loops do: the primal image is
        the candidate (``spp``), and ``dr.backward`` replays paths with independent samples
        (``seed_grad``, ``gradient_spp``): one primal and one adjoint pass per iteration, whatever
        the number of scalars. With an :class:`~services.solver.estimators.losses.ImageLoss` the loss
        and ``dz/dy`` stay on the device and one synchronisation reads back the candidate, ``z``
        and ``dz/dp``. Falls back to separate passes when either does not fit one pass."""
        params = problem.parameters
        width, height = problem.scene.resolution(sensor)
        if max(passes_for(width * height, spp)[0], passes_for(width * height, gradient_spp)[0]) > 1:
            return super().candidate_and_gradient(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                  seed=seed, depth=depth, sensor=sensor)
        with params.tracking():
            image = mi.render(problem.scene.scene, params.params, sensor=sensor, integrator=self.integrator,
                              spp=spp, spp_grad=gradient_spp, seed=opaque_seed(derive_seed(seed, "primal")),
                              # opaque as the primal's: an int would be a kernel literal, a new
                              # kernel every iteration (Mitsuba's stub says int; it takes UInt32)
                              seed_grad=opaque_seed(derive_seed(seed, "adjoint")))  # type: ignore[arg-type]
            if isinstance(loss, ImageLoss):
                rgb = image[..., :3]
                z, dz_dy, bad = loss.device(rgb)
                dr.backward(dr.sum(rgb * dz_dy, axis=None))
                grads = [dr.grad(params.params[key]) for key in params.keys]
                dr.eval(image, z, bad, *grads)
                if int(np.asarray(bad).reshape(-1)[0]):
                    loss.sanitized(loss.WHERE, int(np.asarray(bad).reshape(-1)[0]))
                candidate = np.array(image, dtype=np.float32)[..., :3]
                dz_dp = np.concatenate([np.asarray(g, np.float64).reshape(-1) for g in grads])
                for key in params.keys:
                    dr.clear_grad(params.params[key])
                return candidate, float(np.asarray(z).reshape(-1)[0]), dz_dp
            candidate = np.array(image, dtype=np.float32)[..., :3]
            z, dz_dy = loss(candidate)
            dz_dp = self._backward(params, image, dz_dy)
        return candidate, z, dz_dp

    @staticmethod
    def _backward(params, image, dz_dy: np.ndarray) -> np.ndarray:
        """Adjoint pass of ``Σ dz/dy · image``; returns ``dz/dp`` ``(P,)`` and clears the gradients."""
        padded = np.zeros(tuple(image.shape), np.float32)  # films with an alpha channel render (H, W, 4)
        padded[..., :3] = dz_dy
        dr.backward(dr.sum(image * mi.TensorXf(padded), axis=None))
        dz_dp = np.concatenate([np.asarray(dr.grad(params.params[key]), np.float64).reshape(-1)
                                for key in params.keys])
        for key in params.keys:
            dr.clear_grad(params.params[key])
        return dz_dp

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
                                  spp=per_pass, seed=opaque_seed(derive_seed(seed, "path", k)))
                total += self._backward(params, image, dz_dy)
        return total / passes

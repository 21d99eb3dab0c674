"""``prb``: Mitsuba's Path Replay Backpropagation integrator (Vicini et al. 2021), the reference.

Paths have the job's :class:`~services.solver.estimators.render.PathDepth`: by default unbounded
with Russian roulette from depth 5, as Mitsuba does (unbiased). Sampling is detached in ``prb`` as
in the camera-hit methods: the same parameters are optimizable.

Three entry points, each one pass per spp-pass over the film:

``candidate_and_gradient``  one differentiable render: its primal is the candidate, one adjoint
                            pass gives ``dz/dp`` whatever ``P`` (what an Adam iteration costs);
                            frozen (below)
``images``                  the Jacobian ``dI/dp`` ``(P, H, W, 3)`` by forward mode, one render per
                            *group* of scalars that change distinct RGB channels (an RGB albedo's
                            three components change one channel each: one render for the three)
``candidate_gradient_and_images``  what a second-order iteration needs: the candidate from a
                            primal render, the Jacobian from independent samples, and ``dz/dp =
                            Σ dz/dy · J`` contracted from them (unbiased, no adjoint pass)

Frozen. Mitsuba's tutorial loop re-traces ``prb`` in Python at every iteration: the path loop's
body, the BSDF and emitter calls, the adjoint replay. On a CPU that tracing is a third of a 1-spp
iteration. ``candidate_and_gradient`` runs its render, loss and adjoint pass
(:func:`differentiate`), and ``images`` each forward-mode render (:func:`tangent_render`), through
``dr.freeze``: the first calls of each view (and spp, and group of scalars) record the kernels,
later calls replay them with the current parameter values, seed and target as inputs.
The replay computes what the traced call computes (``tests/unit/test_prb_frozen.py`` compares
them); ``render.freeze: false`` traces every call instead.

Textures freeze too, with ``dz/dp`` read after the call. A frozen function runs in an isolated
gradient scope (``dr.isolate_grad``): the adjoint pass inside it stops at the variables made
before the call, and the edges from those to their own inputs are traversed when the call returns.
Dr.Jit 1.5 stores a 3-channel texture padded to 4 channels, a copy derived from the bitmap's
``data`` by ``params.update()``, outside the call: inside the call the gradient reaches that copy,
not ``data`` (read there, ``dz/dp`` of ``textured-floor``'s texels came out zero); after it,
``data`` has it, recorded or replayed. A scalar value is read by the render itself: inside or
after, the same. Forward mode is seeded into the padded copy before the call
(:func:`push_tangents`): inside it, Dr.Jit refuses to cross that edge.
"""

from __future__ import annotations

import heapq
from typing import ClassVar

import drjit as dr
import mitsuba as mi
import numpy as np

from schemas.methods import Method
from services.solver.estimators.losses import ImageLoss, device_loss
from services.solver.estimators.methods.base import Fields, GradientMethod, Loss, contract
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import PathDepth, opaque_seed, render
from services.solver.sampling.passes import passes_for
from services.solver.seeds import derive_seed


def channel_groups(channels: list[tuple[int, ...]]) -> list[list[int]]:
    """Greedy partition of scalars (given the RGB channels each one changes) into groups whose
    channel sets are pairwise disjoint: one forward-mode render measures a whole group, each
    scalar's derivative read from its own channels. Returns lists of indices into ``channels``.

    Each scalar joins the first group (in creation order) that uses none of its channels, else
    opens a new one. Groups are kept in one min-heap of indices per channel set (a bit mask), so
    that first group is the smallest head among the heaps whose mask is disjoint from the
    scalar's: ``O(n · S log n)`` for ``n`` scalars and ``S`` distinct channel sets (at most 8 for
    RGB), where comparing with every group would be ``O(n²)`` (a mesh's vertex coordinates each
    change all three channels: one group each)."""
    groups: list[list[int]] = []
    heaps: dict[int, list[int]] = {}          # channel mask -> indices of the groups that use exactly it
    for i, chans in enumerate(channels):
        mine = 0
        for c in chans:
            mine |= 1 << c
        if not mine and groups:                # changes no channel: the first group takes it
            groups[0].append(i)
            continue
        free = [mask for mask, heap in heaps.items() if heap and not mask & mine]
        if free:
            mask = min(free, key=lambda m: heaps[m][0])
            g = heapq.heappop(heaps[mask])
            groups[g].append(i)
            heapq.heappush(heaps.setdefault(mask | mine, []), g)
        else:
            groups.append([i])
            heapq.heappush(heaps.setdefault(mine, []), len(groups) - 1)
    return groups


#: Fewest recordings a frozen render keeps (one per view and sample count); beyond its limit the
#: least recently used is dropped and recorded again when needed (:meth:`Prb.fit_views` raises the
#: limit to a job's views).
RECORDINGS = 64
#: Recordings one view may take per configuration: its first two calls may record (the first
#: render evaluates state that the second finds evaluated).
RECORDINGS_PER_VIEW = 2


def differentiate(scene, params, target, seed, *, sensor: int, spp: int, spp_grad: int, integrator, kind: str):
    """One differentiable render of ``sensor`` and the adjoint pass of its loss (Eq. 10), in pure
    Dr.Jit (so that ``dr.freeze`` can record it). ``target`` ``(H, W, 3)``; ``seed`` an opaque
    ``UInt32``: the primal uses it, the adjoint pass Mitsuba's decorrelated ``sample_tea_32(seed,
    1)``. Returns ``(image (H, W, C) detached, z, non-finite pixel count)``; ``dz/dp`` is left in
    the gradients of the parameters (which must track gradients), to be read after the call: a
    frozen call's gradient reaches a texture's ``data`` only when it returns (module docstring)."""
    image = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=spp, spp_grad=spp_grad, seed=seed)
    rgb = image[..., :3]
    z, dz_dy, bad = device_loss(kind, rgb, target)
    dr.backward(dr.sum(rgb * dz_dy, axis=None))
    return dr.detach(image), z, bad


def push_tangents(params, tangents: dict) -> None:
    """Seed forward mode with ``tangents`` (``{key: value-shaped tangent}``) and push them into
    the values derived from the parameters (a bitmap's padded texture), which the render's own
    traversal does not reach. Outside a frozen call: inside it the edges from the parameters to
    those values lie outside its isolated gradient scope, which forward mode may not cross."""
    for key, tangent in tangents.items():
        dr.set_grad(params[key], tangent)
    dr.enqueue(dr.ADMode.Forward, *[params[key] for key in tangents])
    dr.traverse(dr.ADMode.Forward, dr.ADFlag.ClearEdges)


def tangent_render(scene, params, seed, *, sensor: int, spp: int, integrator):
    """The render of ``sensor`` and its forward-mode derivative along the tangents that
    :func:`push_tangents` seeded: ``(I, Σ_i t_i dI/dp_i)``, each ``(H, W, C)``; the primal with
    ``seed``, the tangent with Mitsuba's decorrelated ``seed_grad``. In pure Dr.Jit (so that
    ``dr.freeze`` can record it)."""
    image = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=spp, seed=seed)
    dr.forward_to(image)
    return dr.detach(image), dr.grad(image)


class Prb(GradientMethod):
    """``loss_gradient``: one adjoint (reverse-mode) render per pass, whatever the number of
    scalars ``P``; ``images``: one forward-mode render per channel group and pass."""

    name = Method.PRB
    uses = frozenset()
    geometry_refusal: ClassVar[str | None] = (
        "Mitsuba's prb has no boundary term for moving silhouettes (its documentation: not for geometry); "
        "prb-projective or direct-projective differentiate a pose")
    #: the Mitsuba integrator's type
    integrator_type = "prb"
    #: whether forward mode is pushed from the parameters before the render (:func:`push_tangents`)
    pushes_tangents = True

    def __init__(self, *, depth: PathDepth, radiance: bool = False, differential: bool = False, freeze: bool = True):
        super().__init__(radiance=radiance, differential=differential)
        self.depth = depth
        self.integrator = depth.integrator(self.integrator_type)
        #: whether ``candidate_and_gradient`` replays recorded kernels (module docstring)
        self.freeze = freeze
        self.fit_views(1, 1)

    def fit_views(self, views: int, groups: int) -> None:
        """Size the frozen renders' recording caches for ``views`` sensors and ``groups`` channel
        groups of the Jacobian's forward-mode renders: a view visited in turn must find its
        recording, or a job of more views than the cache holds records at every call (an LRU cache
        cycled by more keys than it holds never hits). Drops the recordings made so far."""
        if views < 1 or groups < 1:
            raise ValueError(f"fit_views needs views >= 1 and groups >= 1, got {views} and {groups}")
        gradient = max(RECORDINGS, RECORDINGS_PER_VIEW * views)
        tangent = max(RECORDINGS, RECORDINGS_PER_VIEW * views * groups)
        self._frozen = dr.freeze(differentiate, limit=gradient, warn_after=gradient)
        self._frozen_tangent = dr.freeze(tangent_render, limit=tangent, warn_after=tangent)

    @classmethod
    def from_effects(cls, effects, depth):
        if depth is None:
            raise ValueError(f"{cls.name} traces paths: it needs a PathDepth (services.solver.estimators.render)")
        return cls(depth=depth)

    # ----------------------------------------------------------- Jacobian

    def gradient_images(self, problem: Problem, fields: Fields, *, spp: int, seed: int, sensor: int = 0) -> np.ndarray:
        return self._jacobian(problem, spp=spp, seed=seed, sensor=sensor)[1]

    def _jacobian(self, problem: Problem, *, spp: int, seed: int, sensor: int) -> tuple[np.ndarray, np.ndarray]:
        """The forward-mode renders of :meth:`images`: ``(y (H, W, 3), J (P, H, W, 3))``, ``y`` the
        renders' primal image. Mitsuba renders a forward-mode pass's tangent with the decorrelated
        ``seed_grad``, so ``y`` and ``J`` share no sample; every group renders the same primal
        samples (the same seed), so ``y`` is one ``spp`` render."""
        params, layout = problem.parameters, problem.layout
        width, height = problem.scene.resolution(sensor)
        passes, per_pass = passes_for(width * height, spp)
        y = np.zeros((height, width, 3), np.float64)
        out = np.zeros((params.n, height, width, 3), np.float64)
        for g, group in enumerate(channel_groups(list(layout.channels))):
            scalars = [layout.scalars[a] for a in group]
            for k in range(passes):
                primal, image = self._forward(problem, scalars, sensor, per_pass, derive_seed(seed, "path", k))
                if g == 0:
                    y += primal
                for a, i in zip(group, scalars):
                    chans = list(layout.channels[a])
                    out[i][..., chans] += image[..., chans]
        return (y / passes).astype(np.float32), (out / passes).astype(np.float32)

    def _forward(self, problem: Problem, scalars: list[int], sensor: int, spp: int,
                 seed: int) -> tuple[np.ndarray, np.ndarray]:
        """One forward-mode render: its primal image and ``Σ_i dI/dp_i`` over ``scalars``, each
        ``(H, W, 3)`` float64."""
        params = problem.parameters
        step = self._frozen_tangent if self.freeze else tangent_render
        with params.tracking():  # re-creates the edges from the parameters to what derives from them
            tangents = params.tangents(scalars)
            if self.pushes_tangents:
                push_tangents({key: params.variable(key) for key in tangents}, tangents)
            else:   # seeded on the leaves only: the render's forward_to carries them (projective: below)
                for key, tangent in tangents.items():
                    dr.set_grad(params.variable(key), tangent)
            primal, tangent = step(problem.scene.scene, params.params, opaque_seed(seed), sensor=sensor, spp=spp,
                                   integrator=self.integrator)
            for key in tangents:
                dr.clear_grad(params.variable(key))
            return np.array(primal, dtype=np.float64)[..., :3], np.array(tangent, dtype=np.float64)[..., :3]

    def candidate_gradient_and_images(self, problem: Problem, fields: Fields, loss: Loss, *, spp: int,
                                      gradient_spp: int, seed: int, depth: PathDepth,
                                      sensor: int = 0) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        """The candidate ``y``, the Jacobian ``J`` (forward mode, ``gradient_spp``) and ``dz/dp =
        Σ_pixels dz/dy · J`` (Eq. 10), unbiased for ``l2`` because ``y`` and ``J`` share no sample.
        No adjoint pass. With ``spp == gradient_spp`` the candidate is the forward-mode renders' own
        primal image (:meth:`_jacobian`: independent of ``J``), which saves the primal render a
        separate candidate costs (a third of the renders of a two-group Jacobian); otherwise a
        ``path`` render at ``spp``."""
        if spp == gradient_spp:
            candidate, images = self._jacobian(problem, spp=gradient_spp, seed=derive_seed(seed, "jacobian"),
                                               sensor=sensor)
        else:
            candidate = render(problem, spp=spp, seed=derive_seed(seed, "candidate"), sensor=sensor, depth=depth)
            images = self.gradient_images(problem, fields, spp=gradient_spp, seed=derive_seed(seed, "jacobian"),
                                          sensor=sensor)
        z, dz_dy = loss(candidate)
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
        if not isinstance(loss, ImageLoss):
            with params.tracking():
                image = mi.render(problem.scene.scene, params.params, sensor=sensor, integrator=self.integrator,
                                  spp=spp, spp_grad=gradient_spp, seed=opaque_seed(derive_seed(seed, "primal")))
                candidate = np.array(image, dtype=np.float32)[..., :3]
                z, dz_dy = loss(candidate)
                dz_dp = self._backward(params, image, dz_dy)
            return candidate, z, dz_dp
        step = self._frozen if self.freeze else differentiate
        with params.tracking():
            image, z, bad = step(problem.scene.scene, params.params, loss.device_target,
                                 opaque_seed(derive_seed(seed, "primal")), sensor=sensor, spp=spp,
                                 spp_grad=gradient_spp, integrator=self.integrator, kind=loss.kind)
            grads = params.gradients()   # after the call: module docstring
            dr.eval(image, z, bad, *grads)
        if int(np.asarray(bad).reshape(-1)[0]):
            loss.sanitized(loss.WHERE, int(np.asarray(bad).reshape(-1)[0]))
        candidate = np.array(image, dtype=np.float32)[..., :3]
        dz_dp = np.concatenate([np.asarray(g, np.float64).reshape(-1) for g in grads])
        return candidate, float(np.asarray(z).reshape(-1)[0]), dz_dp

    @staticmethod
    def _backward(params, image, dz_dy: np.ndarray) -> np.ndarray:
        """Adjoint pass of ``Σ dz/dy · image``; returns ``dz/dp`` ``(P,)`` and clears the gradients."""
        padded = np.zeros(tuple(image.shape), np.float32)  # films with an alpha channel render (H, W, 4)
        padded[..., :3] = dz_dy
        dr.backward(dr.sum(image * mi.TensorXf(padded), axis=None))
        return params.gradient_vector()

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

"""The images a run writes besides its records: the candidate of every view and the gradient
images ``dI/dp`` of every view, on a schedule that keeps them off the iteration's path.

They are for people (the dashboard, the files), not for the optimization: an iteration renders
only its batch of views, and ``prb``'s gradient images cost one forward-mode render per group of
scalars. :class:`ImageSchedule` writes them every ``images_every`` iterations when the job sets it;
otherwise whenever the images written so far took less than ``images_budget`` (5%) of the run's
time, at the last iteration, and whenever the host asks (the dashboard's button).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from schemas.job import JobSpec
from services.solver.estimators.methods import Fields, GradientMethod
from services.solver.estimators.methods.cached import CachedFirstHits
from services.solver.estimators.render import PathDepth, render
from services.solver.scene.silhouettes import overlay, silhouette
from services.solver.seeds import derive_seed


@dataclass
class ImageSchedule:
    """When to write images (module docstring). ``run_seconds`` and ``image_seconds`` count this
    attempt only; ``estimate`` is the last cost of a write (None before the first)."""

    run_seconds: float = 0.0
    image_seconds: float = 0.0
    estimate: float | None = None
    last_iteration: float = 0.0

    def due(self, k: int, spec: JobSpec, *, asked: bool, elapsed: float) -> bool:
        """Whether iteration ``k`` writes images; ``elapsed`` is the iteration's time so far."""
        if asked or k == spec.iterations - 1:
            return True
        if spec.images_every is not None:
            return k % spec.images_every == 0
        expected = self.estimate if self.estimate is not None else 4.0 * elapsed
        # a write now, and the last iteration's (always written) kept within the budget
        later = self.image_seconds + 2 * expected
        return later <= spec.images_budget * (self.run_seconds + elapsed + 2 * expected)

    def spent(self, image_seconds: float, iteration_seconds: float, *, written: bool) -> None:
        self.run_seconds += iteration_seconds
        if written:
            self.image_seconds += image_seconds
            self.estimate = image_seconds


def render_views(prepared, method: GradientMethod, fields: Fields, candidates: dict[int, np.ndarray],
                 k: int, spp: int, gradient_spp: int,
                 depth: PathDepth) -> tuple[dict[int, np.ndarray], dict[int, np.ndarray]]:
    """The candidate ``(H, W, 3)`` and the gradient images ``(P, H, W, 3)`` of every view at the
    current parameters (``candidates`` holds those the iteration rendered already). A job with a
    texture parameter writes no gradient images (P of them would be one per texel): its gradient
    is written as a texture instead (:mod:`.textures`); ``gradients`` is then empty, as for a
    shape parameter (one image per vertex coordinate)."""
    spec, problem = prepared.spec, prepared.problem
    per_scalar = not problem.parameters.has_textures and not problem.parameters.shapes
    renders, gradients = {}, {}
    for sensor in sorted(prepared.targets):
        seed = derive_seed(spec.seed, "images", k, sensor)
        if sensor in candidates:
            image = candidates[sensor]
        elif isinstance(method, CachedFirstHits) and method.field_candidate:
            image = method.cache.candidate(sensor, fields.radiance)
        else:
            image = render(problem, spp=spp, seed=seed, sensor=sensor, depth=depth)
        renders[sensor] = np.nan_to_num(image, nan=0.0, posinf=0.0, neginf=0.0)
        if per_scalar:
            gradients[sensor] = np.nan_to_num(method.gradient_images(problem, fields, spp=gradient_spp, seed=seed,
                                                            sensor=sensor), nan=0.0, posinf=0.0, neginf=0.0)
    return renders, gradients


def silhouette_views(prepared, current: np.ndarray, cache: dict[int, np.ndarray]) -> dict[int, np.ndarray]:
    """A geometry job's silhouettes (:mod:`services.solver.scene.silhouettes`) in every view: its
    overlay ``(H, W, 3)`` in display space, of the moved shapes at ``current`` ``(P,)`` (the
    scene's parameters now) over the target, with the target's silhouette outlined when the
    target's values are known. ``cache`` keeps the target's silhouettes (computed once, at the
    target values, the parameters then put back)."""
    problem = prepared.problem
    params, scene = problem.parameters, problem.scene
    shapes = sorted(set(params.poses) | set(params.shapes))   # posed or reshaped meshes
    if not cache and prepared.target_values is not None:
        try:
            with params.showing_targets(prepared.target_values):   # a target mesh of another topology swapped in
                cache.update({s: silhouette(scene.scene, shapes, scene.sensor(s)) for s in prepared.targets})
        finally:
            params.assign(current)
    return {s: overlay(prepared.targets[s], silhouette(scene.scene, shapes, scene.sensor(s)), cache.get(s))
            for s in sorted(prepared.targets)}


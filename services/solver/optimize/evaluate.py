"""One gradient evaluation at a job's initial parameters (the ``ndrf gradient`` command and the
benchmarks): train the method's fields, then ``dI/dp`` (Eq. 3) and ``dz/dp`` (Eq. 10)."""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.solver.estimators.losses import image_loss
from services.solver.estimators.methods import contract, make_method
from services.solver.estimators.render import render
from services.solver.optimize.build import apply_effects
from services.solver.optimize.resolve import resolve
from services.solver.optimize.setup import prepare
from services.solver.seeds import derive_seed
from services.solver.training.trainer import FieldTrainer, fields_of

log = logging.getLogger(__name__)


@dataclass
class GradientEvaluation:
    """``images[s]``: ``(P, H, W, 3)`` float32 of sensor ``s``; ``summary``: method, seconds, dz/dp, ..."""

    images: dict[int, np.ndarray]
    summary: dict


def evaluate_gradient(spec: JobSpec, method_name: str, *, spp: int, train_steps: int | None = None,
                      scene_file: Path | None = None) -> GradientEvaluation:
    """``dI/dp`` of every sensor with a target at ``spp`` samples per pixel (the caller's choice: the
    job's ``render.gradient_spp`` serves the loop's steps, not one image), after ``train_steps``
    training steps of the method's fields (default: the job's ``training.warmup_steps``)."""
    spec = spec.model_copy(update={"method": method_name, "jacobian": "method"})
    prepared, measures = prepare(spec, scene_file=scene_file)
    recipe = resolve(spec, prepared.problem.parameters, len(prepared.targets), measures)
    apply_effects(prepared, recipe)
    problem = prepared.problem
    if problem.parameters.has_textures:
        raise InvalidJob("parameters", f"the gradient images are one per scalar, {problem.parameters.n} for a texture "
                                       f"job: run the job instead (ndrf run); its images iterations write "
                                       f"textures/<key>.dz_dp.npy, the gradient as a texture")
    if problem.parameters.shapes:
        raise InvalidJob("parameters", f"the gradient images are one per scalar, {problem.parameters.n} for a mesh's "
                                       f"vertices: run the job instead (ndrf run); its records give the Chamfer "
                                       f"distance and its images iterations the mesh (meshes/<shape id>.ply)")
    method = make_method(method_name, problem.effects, recipe.depth)
    steps = spec.training.warmup_steps if train_steps is None else train_steps

    start = time.perf_counter()
    trainer = (FieldTrainer(problem, spec.training, radiance=recipe.radiance, differential=recipe.differential,
                            seed=spec.seed) if recipe.radiance or recipe.differential else None)
    if trainer is not None:
        trainer.train(steps)
    trained = time.perf_counter()
    images, dz_dp, loss = {}, np.zeros(problem.parameters.n), 0.0
    for sensor, target in sorted(prepared.targets.items()):
        images[sensor] = method.gradient_images(problem, fields_of(trainer), spp=spp,
                                       seed=derive_seed(spec.seed, "gradient", sensor), sensor=sensor)
        candidate = render(problem, spp=spec.render.spp, seed=derive_seed(spec.seed, "candidate", sensor),
                           sensor=sensor, depth=recipe.depth)
        z, dz_dy = image_loss(spec.loss, candidate, target)
        loss += z
        dz_dp += contract(images[sensor], dz_dy)
    done = time.perf_counter()
    summary = {
        "method": str(method_name),
        "seconds": done - start,
        "training_seconds": trained - start,
        "gradient_seconds": done - trained,
        "train_steps": steps if trainer is not None else 0,
        "spp": spp,
        "resolution": list(problem.scene.resolution()),
        "labels": problem.parameters.labels,
        "parameters": prepared.init.tolist(),
        "loss": loss,
        "dz_dp": dz_dp.tolist(),
        "sanitized": dict(problem.sanitized),
        "effects": problem.effects.to_json() if problem.effects is not None else None,
    }
    return GradientEvaluation(images, summary)

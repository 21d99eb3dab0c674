"""One gradient evaluation at a job's initial parameters (the ``ndrf gradient`` command)."""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from schemas.job import JobSpec
from schemas.solver import TrainingConfig
from services.estimators.context import Problem
from services.estimators.gradients import Fields, GradientMethod, contract
from services.estimators.methods import make_method
from services.estimators.reference import render
from services.estimators.training import FieldTrainer
from services.optimize.losses import image_loss
from services.optimize.setup import prepare
from services.seeds import derive_seed
from services.store.files import atomic_write_bytes, atomic_write_json, atomic_write_npy
from services.store.images import gradient_png

log = logging.getLogger(__name__)


def make_trainer(problem: Problem, method: GradientMethod, config: TrainingConfig, seed: int) -> FieldTrainer | None:
    """The trainer of exactly the fields ``method`` uses (none for ``direct`` and ``prb``).

    ``L_phi`` is trained when the method queries it, or when ``dL_theta`` is trained and its
    residual contains ``∫ (∂f) L_phi`` (the plan decides; without a plan: whenever ∂f is attached).
    """
    differential = method.needs_differential
    for_residual = problem.plan.radiance_field.value if problem.plan is not None else problem.attach_bsdf
    radiance = method.needs_radiance or (differential and bool(for_residual))
    if not (radiance or differential):
        return None
    return FieldTrainer(problem, config, radiance=radiance, differential=differential, seed=seed)


def fields_of(trainer: FieldTrainer | None) -> Fields:
    return Fields() if trainer is None else Fields(trainer.radiance, trainer.differential)


def write_gradient_images(folder: Path, images: np.ndarray, labels: list[str]) -> list[float]:
    """``gradients.npy`` and one PNG preview per scalar; returns the preview scales."""
    atomic_write_npy(folder / "gradients.npy", images.astype(np.float32))
    scales = []
    for i, label in enumerate(labels):
        png, scale = gradient_png(images[i])
        atomic_write_bytes(folder / f"gradient-{i}.png", png)
        scales.append(scale)
    return scales


def evaluate_gradient(spec: JobSpec, method_name: str, out_dir: Path, *, spp: int | None = None,
                      train_steps: int | None = None, base_dir: Path | None = None) -> dict:
    prepared = prepare(spec, base_dir=base_dir, method=method_name)
    problem = prepared.problem
    method = make_method(method_name, max_depth=spec.render.max_depth, plan=problem.plan)
    spp = spp or spec.render.gradient_spp
    steps = spec.training.warmup_steps if train_steps is None else train_steps

    start = time.perf_counter()
    trainer = make_trainer(problem, method, spec.training, spec.seed)
    if trainer is not None:
        trainer.train(steps)
    trained = time.perf_counter()
    sensor_images, dz_dp, loss = [], np.zeros(problem.parameters.n), 0.0
    for sensor, target in sorted(prepared.targets.items()):
        images = method.images(problem, fields_of(trainer), spp=spp, seed=derive_seed(spec.seed, "gradient", sensor), sensor=sensor)
        candidate = render(problem, spp=spec.render.spp, seed=derive_seed(spec.seed, "candidate", sensor), sensor=sensor,
                           max_depth=spec.render.max_depth)
        z, dz_dy = image_loss(spec.loss, candidate, target)
        loss += z
        dz_dp += contract(images, dz_dy)
        sensor_images.append(images)
    done = time.perf_counter()

    out_dir.mkdir(parents=True, exist_ok=True)
    labels = problem.parameters.labels
    scales = write_gradient_images(out_dir, sensor_images[0], labels)
    for sensor, images in enumerate(sensor_images[1:], start=1):
        write_gradient_images(out_dir / f"sensor-{sensor}", images, labels)
    summary = {
        "method": method_name,
        "seconds": done - start,
        "training_seconds": trained - start,
        "gradient_seconds": done - trained,
        "train_steps": steps if trainer is not None else 0,
        "spp": spp,
        "resolution": list(problem.scene.resolution()),
        "labels": labels,
        "parameters": prepared.init.tolist(),
        "loss": loss,
        "dz_dp": dz_dp.tolist(),
        "preview_scales": scales,
        "sanitized": dict(problem.sanitized),
        "effects": problem.plan.to_json() if problem.plan is not None else None,
    }
    atomic_write_json(out_dir / "summary.json", summary)
    return summary

"""``plan.json``: what a run simulates and why (the recipe with its decisions), the scalars with
their bounds and targets, and the events of the run so far. Written when the run starts and at
every event (a larger batch, a remesh, the stop)."""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from schemas.plan import Plan
from services.solver.backend import describe_device
from services.solver.optimize.run import Run


def describe(run: Run, *, seconds: dict, warm_start: dict | None) -> Plan:
    """``plan.json``: what the run simulates and why (the recipe with its decisions), the scalars
    with their bounds and targets, and the events of the run so far."""
    prepared, recipe, built, state = run.prepared, run.recipe, run.built, run.state
    problem, trainer, textures, spec = prepared.problem, built.trainer, prepared.textures, prepared.spec
    width, height = problem.scene.resolution()
    depths: dict[str, object] = {"render": recipe.depth.describe()}
    if prepared.target_depth is not None:
        depths["target"] = prepared.target_depth.describe()
    if recipe.warnings:
        depths["warnings"] = list(recipe.warnings)
    return Plan(**{
        "method": recipe.method,
        "device": describe_device(),
        "recipe": recipe.to_json(),
        "events": [asdict(e) for e in state.events],
        "realised_by": type(built.method).__name__,
        "fields": {"radiance": trainer is not None and trainer.radiance is not None,
                   "differential": trainer is not None and (trainer.differential is not None
                                                            or trainer.head is not None)},
        "scalars": textures.labels,
        "keys": problem.parameters.keys,
        "init": textures.scalars(prepared.init),
        "lower": _bound(textures.scalars(prepared.lower)),     # None: unbounded (a pose's scalars)
        "upper": _bound(textures.scalars(prepared.upper)),
        "target_values": None if prepared.target_values is None else textures.scalars(prepared.target_values),
        "textures": textures.plan(prepared.init, prepared.lower, prepared.upper, prepared.target_values),
        "shapes": {shape: {**report, "largesteps_lambda": prepared.spec.geometry.largesteps_lambda}   # at init
                   for shape, report in prepared.problem.parameters.shape_reports(prepared.init).items()} or None,
        "sensors": sorted(prepared.targets),
        "resolution": [width, height],
        "depths": depths,
        "prepared_seconds": seconds,
        "render": spec.render.model_dump(mode="json"),
        "training": spec.training.model_dump(mode="json"),
        "effects": recipe.effects.to_json() if recipe.effects is not None else None,
        "iterations": spec.iterations,
        "warm_start": warm_start,
    })


def _bound(values: list[float]) -> list[float | None]:
    """A bound per scalar for JSON: None where there is none (infinite)."""
    return [v if np.isfinite(v) else None for v in values]

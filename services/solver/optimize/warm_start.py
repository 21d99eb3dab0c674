"""Warm starts: a job's fields (and optionally its parameters) taken from another job's
checkpoint, then a short adaptive top-up instead of the warm-up.

``dL_theta`` and ``L_phi`` solve the scene's (differential) rendering equation at the parameters
they were trained at; at other parameters of the same scene they are a close start. The host has
checked that the two jobs share the scene, the parameter keys, the field settings and the effect
overrides (:mod:`services.jobs.warm_start`); here the fields' shapes are checked again by loading
them (a mismatch is an :class:`~schemas.errors.InvalidJob`, never a silently different field).

What is reused: the fields' weights, their output scales and weight averages, and their Adam
states. What is not: the training-step counter (this job's sample seeds start from its own seed),
the parameters unless ``warm_start.parameters``, the optimizer of the parameters, the views'
stream. The top-up trains at this job's starting parameters with the adaptive warm-up
(:class:`~services.solver.training.schedule.StepSchedule`: until both residuals plateau) capped
at ``warm_start.top_up_steps`` (default ``training.warmup_steps // 4``); the step counter then
continues from ``training.warmup_steps``, so iteration 0 trains no further warm-up and later
iterations fine-tune as usual.
"""

from __future__ import annotations

import logging
import time

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.solver.estimators.problem import Problem
from services.solver.optimize.field_views import check_layout, read_state
from services.solver.training.schedule import StepSchedule
from services.solver.training.trainer import FieldTrainer

log = logging.getLogger(__name__)

FIELD = "warm_start.job"


def load_fields(trainer: FieldTrainer, saved: dict | None) -> list[str]:
    """Load the checkpointed trainer state ``saved`` into ``trainer``'s fields; returns the names
    of the fields loaded. Raises :class:`InvalidJob` when a field is missing or does not fit."""
    if not saved or not saved.get("fields"):
        raise InvalidJob(FIELD, "that job trained no field (prb and direct train none)")
    loaded = []
    for name, field in trainer.fields().items():
        if name not in saved["fields"]:
            raise InvalidJob(FIELD, f"that job did not train the {name} field this job needs")
        try:
            field.load_state_dict(saved["fields"][name])
        except RuntimeError as exc:
            raise InvalidJob(FIELD, f"the {name} field does not fit this job (its chosen effects or field "
                                    f"settings differ): {str(exc).splitlines()[0]}") from None
        try:
            trainer.optimizers[name].load_state_dict(saved["optimizers"][name])
        except (KeyError, ValueError) as exc:
            log.info("warm start: fresh Adam state for %s (%s)", name, exc)
        trainer.calibrated[name] = bool(saved.get("calibrated", {}).get(name, True))
        average = trainer.averages.get(name)
        if average is not None:
            if name in saved.get("averages", {}):
                average.load_state_dict(saved["averages"][name])
            else:
                average.average.load_state_dict(field.state_dict())
        loaded.append(name)
    return loaded


def apply_warm_start(spec: JobSpec, blob: bytes, trainer: FieldTrainer | None, problem: Problem,
                     parameters: np.ndarray, lower: np.ndarray, upper: np.ndarray,
                     on_step=None) -> tuple[np.ndarray, dict]:
    """Warm-start ``trainer`` from the checkpoint ``blob`` and top it up at the starting
    parameters; returns those parameters ``(P,)`` and what was reused (for ``plan.json``)."""
    warm = spec.warm_start
    assert warm is not None  # the loop calls this for warm-started jobs only
    if trainer is None:
        raise InvalidJob("warm_start", "this job's method trains no field: there is nothing to warm-start")
    state = read_state(blob)
    try:
        check_layout(problem, state.get("trainer") or {}, "warm-start job")
    except ValueError as exc:
        raise InvalidJob(FIELD, str(exc)) from None
    fields = load_fields(trainer, state.get("trainer"))
    start = np.asarray(parameters, np.float64).copy()
    if warm.parameters:
        source = np.asarray(state["parameters"], np.float64)
        if source.shape != start.shape:
            raise InvalidJob(FIELD, f"that job has {source.size} scalars, this one {start.size}")
        start = np.clip(source, lower, upper)
    problem.parameters.assign(start)
    config = spec.training
    cap = warm.top_up_steps if warm.top_up_steps is not None else config.warmup_steps // 4
    top_up = config.model_copy(update={"adaptive_steps": True, "warmup_steps": cap,
                                       "min_warmup_steps": min(config.min_warmup_steps, cap)})
    started = time.perf_counter()
    steps = StepSchedule(top_up).run(trainer, on_step) if cap > 0 else []
    trainer.check_finite()
    trainer.steps = max(trainer.steps, config.warmup_steps)   # the warm-up is done: fine-tuning from here
    trainer.schedule.warmed = True
    report = {"job": warm.job, "fields": fields, "parameters": bool(warm.parameters),
              "source_iteration": int(state.get("next_iteration", 0)), "source_method": state.get("method"),
              "top_up_steps": len(steps), "top_up_cap": cap, "top_up_seconds": time.perf_counter() - started,
              "warmup_steps_saved": max(0, config.warmup_steps - len(steps))}
    log.info("warm start from job %s: %s", warm.job, report)
    return start, report

"""``"method": "auto"``: time each unbiased method on the job's own scene, run the fastest.

A short trial builds each candidate (``schemas.methods.AUTO_CANDIDATES``: ``prb``, ``ndrf-lhs``,
``ndrf-rhs``) exactly as the loop would and times its parts on the first sensor at the job's own
resolution, spp and path depth; the cost model below turns them into the seconds the job's
iteration budget would take, and the fastest is run. Its prediction, every other candidate's and
the reason are in ``plan.json`` (``auto``).

Cost model. With ``I`` iterations, ``S`` sensors, a run of method ``m`` takes

    T_m = W_m + I · t_m,     t_m = F_m + S · (g_m + ρ · q_m)

    W_m   the warm-up: ``training.warmup_steps`` training steps (0 for prb: no field)
    F_m   the fine-tuning of one iteration: ``training.steps_per_iteration`` steps
    g_m   candidate render + dz/dp of one sensor (``candidate_and_gradient``)        measured
    q_m   the gradient images dy/dp of one sensor (``images``; prb: one forward-   measured
          mode render per scalar)
    ρ     fraction of iterations that need the images: 1 with Gauss-Newton (its Hessian is built
          from them), else 1 / ``images_every``

A training step costs one of three measured amounts, by what the residual pool
(``training.pool``: ``chunks`` batches, each redrawn after ``reuse`` uses) does in it: ``fresh``
(draw a batch: points, incident rays, hits, encodings; then evaluate and step), ``evaluate`` (the
batch exists, BSDF and emitter values are re-evaluated because the parameters changed) and
``reuse`` (the batch is up to date: the fields' steps only). The warm-up's parameters do not
change: a share ``1/reuse`` of its steps is fresh, the rest reuse. After a parameter step, the
first ``min(N_i, chunks)`` steps of an iteration meet stale batches (``1/reuse`` of them fresh,
the rest evaluate), the others reuse. Without the pool every step is fresh. With
``adaptive_steps`` the step counts are caps, so ``T_m`` is an upper bound for the NDRF methods.

The model assumes every candidate needs the same number of iterations, so time to a given error
is in the ratio of ``T_m``: measured in ``bench.regime`` and ``bench.auto`` (with one optimizer
and schedule, ``prb`` and ``ndrf-lhs`` follow nearly the same error per iteration). It does not
hold where a method's gradient is too noisy or too biased to get there at all (``prb``'s
forward-mode Jacobian at few spp under Gauss-Newton; a field that did not fit): ``bench.auto``
reports those cells and the README says which they are.

The trial runs with torch's random state saved and restored, and builds fresh fields for the
chosen method afterwards: an ``auto`` job that picks ``m`` computes what a job naming ``m`` does.
The pick itself depends on measured time, so it is recorded in the checkpoints and a resumed
attempt keeps it.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass
from dataclasses import fields as dataclass_fields

import numpy as np
import torch

from schemas.methods import AUTO_CANDIDATES, Method
from services.solver.estimators.training import FieldTrainer, fields_of
from services.solver.optimize.build import build
from services.solver.optimize.losses import image_loss
from services.solver.optimize.setup import Prepared
from services.solver.seeds import derive_seed

log = logging.getLogger(__name__)

#: Training steps timed per kind of step (fresh, reuse) and method.
TRIAL_STEPS = 3
#: Renders timed per part (gradient, images) and method.
TRIAL_RENDERS = 2
#: Predicted totals within this factor of the fastest count as a tie, broken by ``choose``'s
#: preference order: the trial's timings are not finer than that (``bench.auto`` measures whole
#: runs at 0.85x to 1.5x of their prediction).
TIE = 1.15


@dataclass(frozen=True)
class MeasuredCost:
    """Seconds of one occurrence of each part of an iteration of one method (see the module);
    the three training steps are 0 for a method without fields."""

    method: str
    step_fresh: float
    step_evaluate: float
    step_reuse: float
    gradient: float  # g_m, one sensor
    images: float    # q_m, one sensor


@dataclass(frozen=True)
class Pool:
    """The residual pool's shape (``training.pool``); None in :func:`predict` when it is off."""

    chunks: int
    reuse: int


@dataclass(frozen=True)
class Prediction:
    method: str
    warmup_seconds: float     # W_m
    iteration_seconds: float  # t_m
    total_seconds: float      # T_m
    measured: MeasuredCost


@dataclass(frozen=True)
class Choice:
    method: str
    reason: str
    predictions: list[Prediction]
    trial_seconds: float

    def to_json(self) -> dict:
        return {"picked": self.method, "reason": self.reason, "trial_seconds": self.trial_seconds,
                "predictions": [asdict(p) for p in self.predictions],
                "model": "T = warm-up + iterations * (fine-tuning + sensors * (gradient + rho * images)), the same "
                         "number of iterations assumed for every method (services/solver/optimize/auto.py)"}


def predict(cost: MeasuredCost, *, iterations: int, sensors: int, warmup_steps: int, steps_per_iteration: int,
            images_fraction: float, pool: Pool | None) -> Prediction:
    """``T_m`` of the module's cost model. Pure: the trial's measurements in, seconds out."""
    if not 0.0 <= images_fraction <= 1.0:
        raise ValueError(f"images_fraction must lie in [0, 1], got {images_fraction}")
    if pool is None:
        warmup = warmup_steps * cost.step_fresh
        tuning = steps_per_iteration * cost.step_fresh
    else:
        drawn = 1.0 / pool.reuse
        warmup = warmup_steps * (drawn * cost.step_fresh + (1 - drawn) * cost.step_reuse)
        stale = min(steps_per_iteration, pool.chunks)
        tuning = (stale * (drawn * cost.step_fresh + (1 - drawn) * cost.step_evaluate)
                  + (steps_per_iteration - stale) * cost.step_reuse)
    per_iteration = tuning + sensors * (cost.gradient + images_fraction * cost.images)
    return Prediction(cost.method, warmup, per_iteration, warmup + iterations * per_iteration, cost)


def choose(predictions: list[Prediction], iterations: int,
           preference: tuple[str, ...] = tuple(str(m) for m in AUTO_CANDIDATES)) -> tuple[str, str]:
    """The method with the smallest predicted total, and the reason a user reads. Predictions
    within ``TIE`` of the smallest are a tie (the trial's timings are that noisy), broken by
    ``preference``: ``prb`` first (no field to fit, unbiased from the first iteration), then
    ``ndrf-lhs`` before ``ndrf-rhs`` (at equal time, ``bench.auto``'s Gauss-Newton cell ends 0.11
    from the truth with ``ndrf-lhs`` and 0.30 with ``ndrf-rhs``)."""
    if not predictions:
        raise ValueError("auto has no candidate to choose from")
    ranked = sorted(predictions, key=lambda p: p.total_seconds)
    fastest = ranked[0]
    tied = [p for p in ranked if p.total_seconds <= TIE * fastest.total_seconds]
    best = min(tied, key=lambda p: preference.index(p.method) if p.method in preference else len(preference))

    def said(p: Prediction) -> str:
        warm = f"warm-up {p.warmup_seconds:.1f} s + " if p.warmup_seconds else ""
        return f"{p.method} {p.total_seconds:.1f} s ({warm}{p.iteration_seconds:.3f} s/iteration)"

    others = "; ".join(said(p) for p in ranked if p is not best)
    if best is not fastest:
        return best.method, (f"a tie within the trial's timing noise ({TIE:.2f}x) for {iterations} iterations: "
                             f"{said(best)} against {said(fastest)}; {best.method} is preferred (the more accurate "
                             f"estimator at equal time); all: {others}")
    ratio = (ranked[1].total_seconds / best.total_seconds) if len(ranked) > 1 and best.total_seconds > 0 else math.inf
    reason = (f"predicted fastest for {iterations} iterations: {said(best)}"
              + (f", {ratio:.1f}x ahead of the next; then {others}" if others else ""))
    return best.method, reason


def images_fraction(spec) -> float:
    """ρ of the cost model: the share of iterations that compute gradient images."""
    if spec.optimizer == "gauss-newton":
        return 1.0
    written = len({k for k in range(spec.iterations) if k % spec.images_every == 0} | {spec.iterations - 1})
    return written / spec.iterations


def _seconds(fn: Callable[[], object], repeats: int = 1) -> float:
    """Median seconds of ``repeats`` calls."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return float(np.median(times))


def _training_steps(prepared: Prepared, trainer: FieldTrainer) -> tuple[float, float, float]:
    """``(fresh, evaluate, reuse)`` seconds of a training step (module docstring), timed on the
    trial's trainer: one untimed step (kernel compilation), fresh steps while the pool fills,
    reuse steps once it is full, and evaluate steps after nudging the parameters."""
    pool = prepared.spec.training.pool
    trainer.step()
    if trainer.pool is None or pool.chunks < 2 + TRIAL_STEPS or pool.reuse < 2:
        fresh = _seconds(trainer.step, TRIAL_STEPS)  # too small a pool to tell the kinds apart
        return fresh, fresh, fresh
    fresh = _seconds(trainer.step, TRIAL_STEPS)
    trainer.train(pool.chunks - trainer.steps)  # the rest of the pool's first draw
    reuse = _seconds(trainer.step, TRIAL_STEPS)
    parameters = prepared.problem.parameters
    parameters.assign(np.clip(prepared.init + 1e-3, prepared.lower, prepared.upper))
    evaluate = _seconds(trainer.step, 2)
    parameters.assign(prepared.init)
    return fresh, evaluate, reuse


def measure(prepared: Prepared, name: str) -> MeasuredCost:
    """Time one method's parts on the first sensor, each after one untimed call (kernel
    compilation and first-use caches are paid once per job, not per iteration)."""
    spec, problem = prepared.spec, prepared.problem
    sensor, target = sorted(prepared.targets.items())[0]
    method, trainer = build(prepared, name)
    steps = (0.0, 0.0, 0.0) if trainer is None else _training_steps(prepared, trainer)
    fields = fields_of(trainer)
    seed = derive_seed(spec.seed, "auto", name)

    def gradient() -> None:
        method.candidate_and_gradient(problem, fields, lambda y: image_loss(spec.loss, y, target), spp=spec.render.spp,
                                      gradient_spp=spec.render.gradient_spp, seed=seed, sensor=sensor,
                                      max_depth=prepared.depths["render"])

    def images() -> None:
        method.images(problem, fields, spp=spec.render.gradient_spp, seed=seed, sensor=sensor)

    gradient()
    g = _seconds(gradient, TRIAL_RENDERS)
    q = 0.0
    if images_fraction(spec) > 0:
        images()
        q = _seconds(images, TRIAL_RENDERS)
    return MeasuredCost(name, *steps, gradient=g, images=q)


def choose_method(prepared: Prepared, candidates: tuple[Method, ...] = AUTO_CANDIDATES,
                  between: Callable[[], None] = lambda: None) -> Choice:
    """The trial: measure every candidate, predict, pick (module docstring). ``between`` is called
    before each measurement (the loop's cancel check: it raises to stop). The problem is left
    planned for no method in particular: the caller builds the pick (``build``)."""
    spec = prepared.spec
    started = time.perf_counter()
    predictions = []
    shape = spec.training.pool
    pool = Pool(shape.chunks, shape.reuse) if shape.enabled else None
    with torch.random.fork_rng(devices=[]):
        costs = {}
        for name in candidates:
            between()
            costs[str(name)] = measure(prepared, str(name))
        # The first trainer of a process runs its first tens of steps up to 2x slower (allocators,
        # thread pools warming up), which would count against whichever method is measured first
        first = next((name for name, cost in costs.items() if cost.step_fresh > 0), None)
        if first is not None:
            between()
            again = measure(prepared, first)
            costs[first] = MeasuredCost(first, *(min(getattr(costs[first], f.name), getattr(again, f.name))
                                                 for f in dataclass_fields(MeasuredCost) if f.name != "method"))
    for cost in costs.values():
        predictions.append(predict(cost, iterations=spec.iterations, sensors=len(prepared.targets),
                                   warmup_steps=spec.training.warmup_steps,
                                   steps_per_iteration=spec.training.steps_per_iteration,
                                   images_fraction=images_fraction(spec), pool=pool))
        log.info("auto: %s", cost)
    prepared.problem.parameters.assign(prepared.init)
    picked, reason = choose(predictions, spec.iterations)
    log.info("auto: %s", reason)
    return Choice(picked, reason, sorted(predictions, key=lambda p: p.total_seconds), time.perf_counter() - started)

"""The inverse-rendering loop (paper Sec. 5, Fig. 3b), one iteration at a time:

    1. train / fine-tune L_phi and dL_theta for the current parameters      (Eq. 5-9, Sec. 6.1)
    2. render the candidate y and its loss z(y) against the target(s)        (summed over sensors)
    3. dz/dy
    4.-5. dz/dp = dz/dy · dy/dp with the job's gradient method                (Eq. 3, 10, 11 / Sec. 6.3)
       (``GradientMethod.candidate_and_gradient``: ``prb`` does 2-5 in one differentiable render)
    6. Adam step on p, projected onto the bounds

The loop computes and reports (:class:`~services.solver.optimize.report.RunReporter`); it never
writes a file or a job record. The CLI, the worker and the tests differ only in their reporter.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.methods import AUTO, AUTO_CANDIDATES
from schemas.records import IterationRecord
from services.solver.estimators.methods import GradientMethod
from services.solver.estimators.training import FieldTrainer, fields_of
from services.solver.optimize import checkpoint
from services.solver.optimize.adam import Adam
from services.solver.optimize.auto import choose_method
from services.solver.optimize.build import build
from services.solver.optimize.gauss_newton import gauss_newton_hessian, gauss_newton_step
from services.solver.optimize.losses import image_loss
from services.solver.optimize.report import RunAborted, RunOutcome, RunReporter
from services.solver.optimize.setup import Prepared, prepare
from services.solver.seeds import derive_seed

log = logging.getLogger(__name__)

#: Seconds between two warm-up progress reports.
PROGRESS_SECONDS = 2.0


class Stopped(Exception):
    """The host asked the run to stop: ``"canceled"`` (the job ends) or ``"interrupted"`` (the
    run checkpoints and the host resumes it later)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


@dataclass
class RunState:
    next_iteration: int
    parameters: np.ndarray
    adam: Adam
    history: list = field(default_factory=list)


def learning_rate(spec: JobSpec, k: int) -> float:
    """Geometric decay from ``learning_rate`` to ``learning_rate · final_learning_rate_ratio``."""
    if spec.iterations <= 1:
        return spec.learning_rate
    return spec.learning_rate * spec.final_learning_rate_ratio ** (k / (spec.iterations - 1))


def planned_steps(spec: JobSpec, k: int) -> int:
    """Training steps done by the end of iteration ``k``'s training phase: the warm-up, then
    ``steps_per_iteration`` per iteration. A resumed run trains up to the same count, so it draws
    the samples the uninterrupted run would have drawn."""
    return spec.training.warmup_steps + k * spec.training.steps_per_iteration


class InverseRenderingRun:
    """One execution (attempt) of a job.

    ``scene_file``  the staged XML of an uploaded or local scene (None for built-ins)
    ``resume``      the bytes of a checkpoint to continue from
    """

    def __init__(self, spec: JobSpec, reporter: RunReporter, *, scene_file: Path | None = None,
                 resume: bytes | None = None):
        self.spec = spec
        self.reporter = reporter
        self.scene_file = scene_file
        self.resume = resume
        self.method_name = str(spec.method)  # the method that runs: an auto job's pick once execute() chose

    def execute(self) -> RunOutcome:
        """Run to the end, to a cancel or to an interruption. A job that fails returns a failed
        outcome (never raises); a reporter's exception propagates unchanged."""
        started = time.perf_counter()
        state = trainer = None
        try:
            prepared = prepare(self.spec, scene_file=self.scene_file)
            self.method_name, choice = self._method_name(prepared)
            method, trainer = build(prepared, self.method_name)
            self.reporter.plan(self._plan(prepared, method, trainer, choice))
            state = self._initial_state(prepared, trainer)
            self.reporter.targets(prepared.targets)
            for k in range(state.next_iteration, self.spec.iterations):
                self._stop_if_asked()
                self._iteration(k, prepared, method, trainer, state)
                state.next_iteration = k + 1
                if state.next_iteration % self.spec.checkpoint_every == 0 or state.next_iteration == self.spec.iterations:
                    self._checkpoint(state, trainer)
            return self._outcome("succeeded", state, started)
        except RunAborted:
            raise
        except Stopped as stop:
            log.info("run %s at iteration %s", stop.reason, state.next_iteration if state else 0)
            if stop.reason == "interrupted":
                if state is not None:
                    self._checkpoint(state, trainer)
                return self._outcome("interrupted", state, started)
            return self._outcome("canceled", state, started)
        except InvalidJob as exc:
            return self._outcome("failed", state, started, error=str(exc), field=exc.field)
        except FloatingPointError as exc:
            k = state.next_iteration if state else 0
            return self._outcome("failed", state, started, error=f"iteration {k}: {exc}")
        except Exception as exc:  # recorded, never silent; the host decides what else to do
            log.exception("run failed")
            return self._outcome("failed", state, started, error=f"{type(exc).__name__}: {exc}")

    # -------------------------------------------------------------- phases

    def _method_name(self, prepared: Prepared) -> tuple[str, dict | None]:
        """The job's method; for ``auto``, the trial's pick (``services.solver.optimize.auto``), or
        on resume the pick the checkpoint recorded (timings differ between attempts; the method
        must not)."""
        if self.spec.method != AUTO:
            return str(self.spec.method), None
        saved = checkpoint.method_of(self.resume) if self.resume is not None else None
        if saved is not None:
            return saved, {"picked": saved, "reason": "picked by an earlier attempt of this job (its checkpoint)"}
        self.reporter.progress("auto", {"candidates": [str(m) for m in AUTO_CANDIDATES]})
        choice = choose_method(prepared, between=self._stop_if_asked)
        return choice.method, choice.to_json()

    def _stop_if_asked(self) -> None:
        reason = self.reporter.should_stop()
        if reason:
            raise Stopped(reason)

    def _initial_state(self, prepared: Prepared, trainer: FieldTrainer | None) -> RunState:
        adam = Adam(prepared.problem.parameters.n, self.spec.learning_rate, *self.spec.adam_betas)
        state = RunState(0, prepared.init.copy(), adam)
        if self.resume is not None:
            saved = checkpoint.loads(self.resume, self.spec)
            state.next_iteration = saved["next_iteration"]
            state.parameters = np.asarray(saved["parameters"], np.float64)
            adam.load_state_dict(saved["adam"])
            if trainer is not None and saved["trainer"] is not None:
                trainer.load_state_dict(saved["trainer"])
            self.reporter.progress("resumed", {"iteration": state.next_iteration,
                                               "training_steps": trainer.steps if trainer else 0})
        prepared.problem.parameters.assign(state.parameters)
        return state

    def _train(self, trainer: FieldTrainer | None, k: int) -> dict:
        if trainer is None:
            return {}
        adaptive = self.spec.training.adaptive_steps
        planned = planned_steps(self.spec, k)
        steps = max(0, planned - trainer.steps)
        warmup = trainer.steps < self.spec.training.warmup_steps and (not adaptive or not trainer.schedule.warmed)
        last = time.monotonic()

        def on_step(stats) -> None:
            nonlocal last
            self._stop_if_asked()
            if warmup and time.monotonic() - last >= PROGRESS_SECONDS:
                last = time.monotonic()
                self.reporter.progress("warmup", {"steps": trainer.steps, "planned": planned,
                                                  "residual_primal": stats.primal_loss,
                                                  "residual_differential": stats.differential_loss})

        # fixed: up to the planned count (a resumed run trains what the uninterrupted one would have);
        # adaptive: until the residual norms say the fields have caught up (training.adaptive_steps)
        stats = trainer.train_iteration(on_step) if adaptive else trainer.train(steps, on_step)
        steps = len(stats)
        trainer.check_finite()
        primal = [s.primal_loss for s in stats if s.primal_loss is not None and np.isfinite(s.primal_loss)]
        differential = [s.differential_loss for s in stats
                        if s.differential_loss is not None and np.isfinite(s.differential_loss)]
        return {"training_steps": steps, "residual_primal": float(np.mean(primal)) if primal else None,
                "residual_differential": float(np.mean(differential)) if differential else None}

    def _iteration(self, k: int, prepared: Prepared, method: GradientMethod, trainer: FieldTrainer | None,
                   state: RunState) -> None:
        spec, problem = self.spec, prepared.problem
        write_images = k % spec.images_every == 0 or k == spec.iterations - 1
        t0 = time.perf_counter()
        training = self._train(trainer, k)
        t1 = time.perf_counter()
        fields = fields_of(trainer)
        loss, dz_dp, renders, gradients = 0.0, np.zeros(problem.parameters.n), {}, {}
        newton = spec.optimizer == "gauss-newton"
        hessian = np.zeros((problem.parameters.n, problem.parameters.n))
        gradient_seconds = image_seconds = 0.0
        for sensor, target in sorted(prepared.targets.items()):
            r0 = time.perf_counter()
            seed = derive_seed(spec.seed, "iteration", k, sensor)

            def loss_of(candidate: np.ndarray, target=target) -> tuple[float, np.ndarray]:
                return image_loss(spec.loss, _finite(problem, "candidate pixels (non-finite)", candidate), target)

            candidate, z, dz_dp_sensor = method.candidate_and_gradient(
                problem, fields, loss_of, spp=spec.render.spp, gradient_spp=spec.render.gradient_spp, seed=seed,
                sensor=sensor, max_depth=prepared.depths["render"])
            dz_dp += dz_dp_sensor
            loss += z
            r1 = time.perf_counter()
            if newton and spec.hessian == "cross":  # two independent halves: an unbiased JᵀJ
                halves = [_finite(problem, "gradient pixels (non-finite)",
                                  method.images(problem, fields, spp=max(1, spec.render.gradient_spp // 2),
                                                seed=derive_seed(seed, "gradient", half), sensor=sensor))
                          for half in ("a", "b")]
                hessian += gauss_newton_hessian(*halves)
                images = (halves[0] + halves[1]) / 2
            elif write_images or newton:  # the samples loss_gradient used (camera-hit methods): images match dz/dp
                images = _finite(problem, "gradient pixels (non-finite)",
                                 method.images(problem, fields, spp=spec.render.gradient_spp,
                                               seed=derive_seed(seed, "gradient"), sensor=sensor))
                if newton:
                    hessian += gauss_newton_hessian(images)
            if write_images:
                renders[sensor] = np.nan_to_num(candidate, nan=0.0, posinf=0.0, neginf=0.0)  # counted in loss_of
                gradients[sensor] = images
            image_seconds += time.perf_counter() - r1
            gradient_seconds += r1 - r0
        lr = learning_rate(spec, k)
        if newton:
            updated = gauss_newton_step(state.parameters, dz_dp, hessian, prepared.lower, prepared.upper, lr=lr,
                                        damping=spec.damping)
        else:
            updated = state.adam.step(state.parameters, dz_dp, prepared.lower, prepared.upper, lr=lr)
        problem.parameters.assign(updated)
        record = IterationRecord(
            iteration=k, loss=loss, parameters=state.parameters.tolist(), updated_parameters=updated.tolist(),
            dz_dp=dz_dp.tolist(), learning_rate=lr, images=write_images, sanitized=dict(problem.sanitized),
            seconds={"training": t1 - t0, "gradient": gradient_seconds, "images": image_seconds},
            parameter_error=(float(np.max(np.abs(state.parameters - prepared.target_values)))
                             if prepared.target_values is not None else None),
            **training)
        state.parameters = updated
        state.history.append(record)
        self.reporter.iteration(record, renders or None, gradients or None)

    # -------------------------------------------------------------- reports

    def _plan(self, prepared: Prepared, method: GradientMethod, trainer: FieldTrainer | None,
              choice: dict | None) -> dict:
        problem = prepared.problem
        width, height = problem.scene.resolution()
        return {
            "method": self.method_name,
            "auto": choice,
            "realised_by": type(method).__name__,
            "fields": {"radiance": trainer is not None and trainer.radiance is not None,
                       "differential": trainer is not None and trainer.differential is not None},
            "scalars": problem.parameters.labels,
            "keys": problem.parameters.keys,
            "init": prepared.init.tolist(),
            "lower": prepared.lower.tolist(),
            "upper": [u if np.isfinite(u) else None for u in prepared.upper.tolist()],
            "target_values": None if prepared.target_values is None else prepared.target_values.tolist(),
            "sensors": sorted(prepared.targets),
            "resolution": [width, height],
            "depths": prepared.depths,
            "render": self.spec.render.model_dump(mode="json"),
            "training": self.spec.training.model_dump(mode="json"),
            "effects": problem.plan.to_json() if problem.plan is not None else None,
            "iterations": self.spec.iterations,
        }

    def _checkpoint(self, state: RunState, trainer: FieldTrainer | None) -> None:
        blob = checkpoint.dumps(spec=self.spec, next_iteration=state.next_iteration, parameters=state.parameters,
                                adam=state.adam.state_dict(), trainer=None if trainer is None else trainer.state_dict(),
                                method=self.method_name)
        self.reporter.checkpoint(blob, state.next_iteration)

    def _outcome(self, status: str, state: RunState | None, started: float, error: str | None = None,
                 field: str | None = None) -> RunOutcome:
        return RunOutcome(status=status, iterations=state.next_iteration if state is not None else 0,
                          seconds=time.perf_counter() - started,
                          parameters=state.parameters.tolist() if state is not None else None,
                          error=error, field=field)


def _finite(problem, what: str, array: np.ndarray) -> np.ndarray:
    """Zero non-finite entries, counted in the job's metrics (never silently)."""
    bad = ~np.isfinite(array)
    if bad.any():
        problem.count_sanitized(what, int(bad.sum()))
        array = np.where(bad, 0.0, array).astype(array.dtype)
    return array

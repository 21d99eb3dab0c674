"""The inverse-rendering loop (paper Sec. 5, Fig. 3b), one iteration at a time:

    1. train / fine-tune L_phi and dL_theta for the current parameters      (Eq. 5-9, Sec. 6.1)
    2. render the candidate y and its loss z(y) against the target(s)        (summed over sensors)
    3. dz/dy
    4. dy/dp with the job's gradient method                                  (Eq. 3, 11 / Sec. 6.3)
    5. dz/dp = dz/dy · dy/dp                                                 (Eq. 10)
    6. Adam step on p, projected onto the bounds

A run writes the job folder of :mod:`services.store.layout`; the CLI and the service's workers
run the same code and differ only in their :class:`RunHooks`.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from schemas.job import JobSpec
from services.estimators.gradients import contract
from services.estimators.methods import make_method
from services.estimators.reference import render
from services.optimize import checkpoint
from services.optimize.adam import Adam
from services.optimize.gradient import fields_of, make_trainer, write_gradient_images
from services.optimize.losses import image_loss
from services.errors import JobError
from services.optimize.setup import Prepared, prepare
from services.seeds import derive_seed
from services.store.files import atomic_write_bytes, atomic_write_npy
from services.store.images import srgb_png
from services.store.layout import JobFolder, now_iso

log = logging.getLogger(__name__)


class Stopped(Exception):
    """The host asked the run to stop at an iteration boundary: ``reason`` is ``"canceled"`` (the
    user's cancel: the job ends) or ``"interrupted"`` (the worker shuts down: the job is
    checkpointed and goes back to the queue)."""

    def __init__(self, reason: str):
        super().__init__(reason)
        self.reason = reason


class Fenced(Exception):
    """This attempt no longer owns the job (its lease was taken over): stop without writing."""


@dataclass
class RunHooks:
    """How a run talks to its host.

    on_event     called with every event after it is appended to the job's log
    should_stop  polled at each iteration boundary: None to go on, "canceled" or "interrupted"
    guard        called before every write; raises :class:`Fenced` if this attempt no longer
                 owns the job
    attempt      identifier of this attempt, stored in checkpoints and events
    """

    on_event: Callable[[dict], None] = lambda event: None
    should_stop: Callable[[], str | None] = lambda: None
    guard: Callable[[], None] = lambda: None
    attempt: str | None = None


@dataclass
class RunState:
    next_iteration: int
    parameters: np.ndarray
    adam: Adam
    seconds: float = 0.0
    history: list = field(default_factory=list)


def learning_rate(spec: JobSpec, k: int) -> float:
    """Geometric decay from ``learning_rate`` to ``learning_rate · final_learning_rate_ratio``."""
    if spec.iterations <= 1:
        return spec.learning_rate
    return spec.learning_rate * spec.final_learning_rate_ratio ** (k / (spec.iterations - 1))


class InverseRenderingRun:
    """One execution (attempt) of a job in a job folder."""

    def __init__(self, spec: JobSpec, folder: JobFolder, hooks: RunHooks | None = None, base_dir: Path | None = None):
        self.spec = spec
        self.folder = folder
        self.hooks = hooks or RunHooks()
        self.base_dir = base_dir

    # ------------------------------------------------------------------ events

    def emit(self, kind: str, **payload) -> dict:
        self.hooks.guard()
        event = self.folder.append_event({"type": kind, "attempt": self.hooks.attempt, **payload})
        self.hooks.on_event(event)
        return event

    def set_status(self, status: str, **extra) -> None:
        self.set_record(status=status, **extra)
        self.emit("status", status=status, **extra)

    # -------------------------------------------------------------------- run

    def execute(self, resume: bool = False) -> dict:
        """Run to the end (or to a cancel); returns the summary. Never raises for a job that
        fails: the failure is recorded (status ``failed``, error message) and returned."""
        started = time.perf_counter()
        self.folder.root.mkdir(parents=True, exist_ok=True)
        if not self.folder.spec_path.is_file():
            self.folder.write("spec.json", self.spec.model_dump(mode="json"))
        state = None
        try:
            self.set_status("running", started=self.folder.read("record.json", {}).get("started") or now_iso())
            prepared = prepare(self.spec, base_dir=self.base_dir, folder=self.folder.root / "scene")
            method = make_method(self.spec.method, max_depth=self.spec.render.max_depth, plan=prepared.problem.plan)
            trainer = make_trainer(prepared.problem, method, self.spec.training, self.spec.seed)
            self._write_plan(prepared, method, trainer)
            state = self._initial_state(prepared, trainer, resume)
            self._write_targets(prepared)
            for k in range(state.next_iteration, self.spec.iterations):
                reason = self.hooks.should_stop()
                if reason:
                    raise Stopped(reason)
                self._iteration(k, prepared, method, trainer, state)
                state.next_iteration = k + 1
                if state.next_iteration % self.spec.checkpoint_every == 0 or state.next_iteration == self.spec.iterations:
                    self._checkpoint(state, trainer)
            return self._finish("succeeded", state, started)
        except Fenced:
            log.warning("attempt %s lost the job: stopping without further writes", self.hooks.attempt)
            raise
        except Stopped as stop:
            log.info("job %s at iteration %s", stop.reason, state.next_iteration if state else 0)
            if stop.reason == "interrupted":
                if state is not None and state.next_iteration > 0:
                    self._checkpoint(state, trainer)
                self.set_status("queued", note="interrupted: the worker stopped; resumes from its checkpoint")
                return {"status": "interrupted", "iterations": state.next_iteration if state else 0}
            return self._finish("canceled", state, started)
        except JobError as exc:
            return self._finish("failed", state, started, error=str(exc), field=exc.field)
        except FloatingPointError as exc:
            k = state.next_iteration if state else 0
            return self._finish("failed", state, started, error=f"iteration {k}: {exc}")
        except Exception as exc:  # recorded, never silent; the host decides whether to retry
            log.exception("job failed")
            return self._finish("failed", state, started, error=f"{type(exc).__name__}: {exc}")

    # -------------------------------------------------------------- phases

    def _initial_state(self, prepared: Prepared, trainer, resume: bool) -> RunState:
        adam = Adam(prepared.problem.parameters.n, self.spec.learning_rate, *self.spec.adam_betas)
        state = RunState(0, prepared.init.copy(), adam)
        if resume and self.folder.checkpoint_path.is_file():
            saved = checkpoint.load(self.folder.checkpoint_path, self.spec)
            state.next_iteration = saved["next_iteration"]
            state.parameters = np.asarray(saved["parameters"], np.float64)
            adam.load_state_dict(saved["adam"])
            if trainer is not None and saved["trainer"] is not None:
                trainer.load_state_dict(saved["trainer"])
            self.folder.drop_iterations_after(state.next_iteration - 1)
            self.emit("resumed", iteration=state.next_iteration)
        prepared.problem.parameters.assign(state.parameters)
        return state

    def _train(self, trainer, k: int) -> dict:
        if trainer is None:
            return {}
        steps = self.spec.training.warmup_steps if trainer.steps == 0 else self.spec.training.steps_per_iteration
        stats = trainer.train(steps)
        trainer.check_finite()
        primal = [s.primal_loss for s in stats if s.primal_loss is not None and np.isfinite(s.primal_loss)]
        differential = [s.differential_loss for s in stats
                        if s.differential_loss is not None and np.isfinite(s.differential_loss)]
        return {"training_steps": steps, "residual_primal": float(np.mean(primal)) if primal else None,
                "residual_differential": float(np.mean(differential)) if differential else None}

    def _iteration(self, k: int, prepared: Prepared, method, trainer, state: RunState) -> None:
        spec, problem = self.spec, prepared.problem
        t0 = time.perf_counter()
        training = self._train(trainer, k)
        t1 = time.perf_counter()
        loss, dz_dp, renders, gradient_images, render_seconds = 0.0, np.zeros(problem.parameters.n), {}, {}, 0.0
        for sensor, target in sorted(prepared.targets.items()):
            r0 = time.perf_counter()
            candidate = render(problem, spp=spec.render.spp, seed=derive_seed(spec.seed, "candidate", k, sensor),
                               sensor=sensor, max_depth=spec.render.max_depth)
            candidate = self._finite(problem, "candidate pixels (non-finite)", candidate)
            z, dz_dy = image_loss(spec.loss, candidate, target)
            render_seconds += time.perf_counter() - r0
            images = method.images(problem, fields_of(trainer), spp=spec.render.gradient_spp,
                                   seed=derive_seed(spec.seed, "gradient", k, sensor), sensor=sensor)
            images = self._finite(problem, "gradient pixels (non-finite)", images)
            loss += z
            dz_dp += contract(images, dz_dy)
            renders[sensor], gradient_images[sensor] = candidate, images
        t2 = time.perf_counter()
        lr = learning_rate(spec, k)
        updated = state.adam.step(state.parameters, dz_dp, prepared.lower, prepared.upper, lr=lr)
        problem.parameters.assign(updated)
        seconds = {"training": t1 - t0, "rendering": render_seconds, "gradient": t2 - t1 - render_seconds}
        record = {
            "iteration": k,
            "loss": loss,
            "parameters": state.parameters.tolist(),
            "updated_parameters": updated.tolist(),
            "dz_dp": dz_dp.tolist(),
            "learning_rate": lr,
            "seconds": seconds,
            "sanitized": dict(problem.sanitized),
            **training,
        }
        if prepared.target_values is not None:
            record["parameter_error"] = float(np.max(np.abs(state.parameters - prepared.target_values)))
        state.parameters = updated
        state.history.append(record)
        self._write_iteration(k, record, renders, gradient_images, problem.parameters.labels)

    @staticmethod
    def _finite(problem, what: str, array: np.ndarray) -> np.ndarray:
        """Zero non-finite entries, counted in the job's metrics (never silently)."""
        bad = ~np.isfinite(array)
        if bad.any():
            problem.count_sanitized(what, int(bad.sum()))
            array = np.where(bad, 0.0, array).astype(array.dtype)
        return array

    # --------------------------------------------------------------- writes

    def _write_plan(self, prepared: Prepared, method, trainer) -> None:
        problem = prepared.problem
        width, height = problem.scene.resolution()
        plan = {
            "method": method.name,
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
            "render": self.spec.render.model_dump(mode="json"),
            "training": self.spec.training.model_dump(mode="json"),
            "effects": problem.plan.to_json() if problem.plan is not None else None,
            "iterations": self.spec.iterations,
        }
        self.hooks.guard()
        self.folder.write("plan.json", plan)
        self.emit("plan", plan=plan)

    def _write_targets(self, prepared: Prepared) -> None:
        for sensor, image in prepared.targets.items():
            if not self.folder.target_path(sensor, "npy").is_file():
                self.hooks.guard()
                atomic_write_npy(self.folder.target_path(sensor, "npy"), image)
                atomic_write_bytes(self.folder.target_path(sensor, "png"), srgb_png(image))

    def _write_iteration(self, k: int, record: dict, renders: dict, gradients: dict, labels: list[str]) -> None:
        self.hooks.guard()
        folder = self.folder.iteration_dir(k)
        if k % self.spec.images_every == 0 or k == self.spec.iterations - 1:
            for sensor, image in renders.items():
                atomic_write_bytes(folder / ("render.png" if sensor == 0 else f"render-{sensor}.png"), srgb_png(image))
            for sensor, images in gradients.items():
                scales = write_gradient_images(folder if sensor == 0 else folder / f"sensor-{sensor}", images, labels)
                if sensor == min(gradients):
                    record["preview_scales"] = scales
            record["images"] = True
        self.folder.write(f"iterations/{k:06d}/record.json", record)
        self.set_record(iteration=k)
        self.emit("iteration", **record)

    def set_record(self, **fields) -> None:
        self.hooks.guard()
        self.folder.write("record.json", self.folder.read("record.json", {}) | fields | {"updated": now_iso()})

    def _checkpoint(self, state: RunState, trainer) -> None:
        self.hooks.guard()
        checkpoint.save(self.folder.checkpoint_path, spec=self.spec, next_iteration=state.next_iteration,
                        parameters=state.parameters, adam=state.adam.state_dict(),
                        trainer=None if trainer is None else trainer.state_dict(), attempt=self.hooks.attempt)
        self.emit("checkpoint", iteration=state.next_iteration)

    def _finish(self, status: str, state: RunState | None, started: float,
                error: str | None = None, field: str | None = None) -> dict:
        plan = self.folder.read("plan.json", {})
        parameters = state.parameters.tolist() if state is not None else None
        summary = {
            "status": status,
            "method": self.spec.method,
            "iterations": state.next_iteration if state is not None else 0,
            "seconds": time.perf_counter() - started,
            "scalars": plan.get("scalars"),
            "init": plan.get("init"),
            "final": parameters,
            "target": plan.get("target_values"),
            "error": error,
            "field": field,
        }
        if parameters is not None and plan.get("target_values") is not None:
            summary["max_abs_error"] = float(np.max(np.abs(np.asarray(parameters) - np.asarray(plan["target_values"]))))
        self.folder.write("summary.json", summary)
        self.set_status(status, error=error, field=field)
        return summary

"""The inverse-rendering loop (paper Sec. 5, Fig. 3b), one iteration at a time:

    1. train / fine-tune L_phi and dL_theta for the current parameters      (Eq. 5-9, Sec. 6.1)
    2. render the candidate y of each view of the iteration's batch and     (a mini-batch of views,
       its loss z(y) against the target                                      scaled to the sum)
    3. dz/dy
    4.-5. dz/dp = dz/dy · dy/dp with the job's gradient method                (Eq. 3, 10, 11 / Sec. 6.3)
       (``GradientMethod.candidate_and_gradient``: ``prb`` does 2-5 in one differentiable render),
       and for a second-order step the Jacobian J = dy/dp of the same views
    6. a step of the optimizer (Adam, Gauss-Newton, Levenberg-Marquardt), projected onto the bounds

What runs is the :class:`~services.solver.optimize.recipe.Recipe` (the job's choices, or the
product's for ``auto``), and the run itself may change it (a larger batch of views or samples
when the steps turn noise-dominated); every decision is in the plan. Renders of every view and gradient images are
written on a budget (``images_every`` / ``images_budget``) and when the host asks for them.

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
from schemas.outcomes import Outcome
from schemas.records import IterationRecord
from services.solver.backend import describe_device
from services.solver.estimators.losses import ImageLoss
from services.solver.estimators.methods import GradientMethod
from services.solver.optimize import checkpoint
from services.solver.optimize.background import BackgroundReporter
from services.solver.optimize.build import Built, build
from services.solver.optimize.images import ImageSchedule, render_views
from services.solver.optimize.optimizers import ParameterOptimizer, make_optimizer
from services.solver.optimize.optimizers.gauss_newton import BLOCK, hessian_of, jacobian_matrix
from services.solver.optimize.recipe import Recipe, choose_recipe, grow_batch
from services.solver.optimize.regularize import regularized
from services.solver.optimize.report import RunAborted, RunOutcome, RunReporter, StopReason
from services.solver.optimize.setup import Prepared, prepare
from services.solver.optimize.textures import TextureReport, record_fields
from services.solver.optimize.views import ViewStream
from services.solver.scene.closure import closure
from services.solver.scene.facts import direct_reach
from services.solver.seeds import derive_seed
from services.solver.training.trainer import FieldTrainer, fields_of

log = logging.getLogger(__name__)

#: Seconds between two warm-up progress reports.
PROGRESS_SECONDS = 2.0
#: A remembered Jacobian counts for the curvature while the parameters are within this many
#: learning rates of where it was taken (:meth:`InverseRenderingRun._curvature`).
FRESH = 2.0


class Stopped(Exception):
    """The host asked the run to stop: ``canceled`` (the job ends) or ``interrupted`` (the run
    checkpoints and the host resumes it later)."""

    def __init__(self, reason: StopReason):
        super().__init__(reason)
        self.reason = reason


@dataclass
class RunState:
    """What a resumed run restores: the next iteration, the parameters, the optimizer's state,
    the position in the stream of views, the batch size, the curvature in use and each view's
    last Jacobian (the ``successive`` curvature's partner)."""

    next_iteration: int
    parameters: np.ndarray
    optimizer: ParameterOptimizer
    views_offset: int = 0
    hessian: np.ndarray | None = None
    #: each view's last two (block-averaged) Jacobians, with the parameters they were taken at
    jacobians: dict[int, list[tuple[np.ndarray, np.ndarray]]] = field(default_factory=dict)
    images: ImageSchedule = field(default_factory=ImageSchedule)
    losses: dict[int, ImageLoss] = field(default_factory=dict)   # each view's loss (its target on the device)


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
                 resume: bytes | None = None, warm: bytes | None = None):
        self.spec = spec
        self.reporter = reporter
        self.scene_file = scene_file
        self.resume = resume
        self.warm = warm            # the checkpoint of spec.warm_start's job (services.solver.optimize.warm_start)
        self.warm_report: dict | None = None
        self.method_name = str(spec.method)  # the method that runs: an auto job's choice once execute() made it
        self.listed: TextureReport | None = None  # which scalars reports list (textures are summarised)

    def execute(self) -> RunOutcome:
        """Run to the end, to a cancel or to an interruption. A job that fails returns a failed
        outcome (never raises); a reporter's exception propagates unchanged. Reports are written
        on a thread of their own while the loop computes (:mod:`.background`)."""
        host = self.reporter
        background = BackgroundReporter(host)
        self.reporter = background
        try:
            return self._execute()
        finally:
            self.reporter = host
            background.close()

    def _execute(self) -> RunOutcome:
        started = time.perf_counter()
        state = trainer = None
        try:
            prepared = prepare(self.spec, scene_file=self.scene_file,
                               on_phase=lambda what: self.reporter.progress("preparing", {"what": what}))
            self.listed = prepared.textures
            decided = time.perf_counter()
            recipe = choose_recipe(self.spec, prepared.problem, len(prepared.targets),
                                   closure=lambda: closure(prepared.problem.scene, seed=self.spec.seed),
                                   direct=lambda: direct_reach(prepared.problem.scene, prepared.problem.parameters,
                                                               seed=self.spec.seed))
            prepared.seconds["recipe"] = time.perf_counter() - decided   # its measurements (closure, reach)
            self.method_name = recipe.method
            built = build(prepared, recipe.method, recipe.jacobian)
            trainer = built.trainer
            state = self._initial_state(prepared, recipe, trainer)
            self.reporter.plan(self._plan(prepared, built, recipe))
            self.reporter.targets(prepared.targets)
            if prepared.textures.targets(prepared.target_values):   # final/<key>.target, for comparison
                self.reporter.textures(None, prepared.textures.targets(prepared.target_values))
            stream = ViewStream(sorted(prepared.targets), derive_seed(self.spec.seed, "batches"))
            for k in range(state.next_iteration, self.spec.iterations):
                self._stop_if_asked()
                grown = self._iteration(k, prepared, built, recipe, stream, state)
                state.next_iteration = k + 1
                if grown:
                    self.reporter.plan(self._plan(prepared, built, recipe))
                if state.next_iteration % self.spec.checkpoint_every == 0 or state.next_iteration == self.spec.iterations:
                    self._checkpoint(state, recipe, trainer)
            if prepared.textures:
                self.reporter.textures(None, prepared.textures.images(state.parameters))
            if isinstance(self.reporter, BackgroundReporter):
                self.reporter.flush()  # success only once every report is written
            return self._outcome(Outcome.SUCCEEDED, state, started)
        except RunAborted:
            raise
        except Stopped as stop:
            log.info("run %s at iteration %s", stop.reason, state.next_iteration if state else 0)
            if stop.reason == Outcome.INTERRUPTED:
                if state is not None:
                    self._checkpoint(state, recipe, trainer)
                return self._outcome(Outcome.INTERRUPTED, state, started)
            return self._outcome(Outcome.CANCELED, state, started)
        except InvalidJob as exc:
            return self._outcome(Outcome.FAILED, state, started, error=str(exc), field=exc.field)
        except FloatingPointError as exc:
            k = state.next_iteration if state else 0
            return self._outcome(Outcome.FAILED, state, started, error=f"iteration {k}: {exc}")
        except Exception as exc:  # recorded, never silent; the host decides what else to do
            log.exception("run failed")
            return self._outcome(Outcome.FAILED, state, started, error=f"{type(exc).__name__}: {exc}")

    # -------------------------------------------------------------- phases

    def _stop_if_asked(self) -> None:
        reason = self.reporter.should_stop()
        if reason:
            raise Stopped(reason)

    def _initial_state(self, prepared: Prepared, recipe: Recipe, trainer: FieldTrainer | None) -> RunState:
        spec = self.spec
        optimizer = make_optimizer(recipe.optimizer, prepared.problem.parameters.n, lr=spec.learning_rate,
                                   betas=spec.adam_betas, damping=spec.damping, trust_growth=recipe.trust_growth,
                                   trust_start=recipe.trust_start)
        state = RunState(0, prepared.init.copy(), optimizer)
        if self.resume is not None:
            saved = checkpoint.loads(self.resume, spec)
            state.next_iteration = saved["next_iteration"]
            state.parameters = np.asarray(saved["parameters"], np.float64)
            optimizer.load_state_dict(saved["optimizer"])
            state.views_offset = int(saved["views_offset"])
            recipe.views, recipe.spp, recipe.gradient_spp = (int(v) for v in saved["batch"])
            state.hessian = None if saved["hessian"] is None else np.asarray(saved["hessian"], np.float64)
            state.jacobians = {int(s): [(np.asarray(at, np.float64), np.asarray(j, np.float64)) for at, j in pairs]
                               for s, pairs in saved["jacobians"].items()}
            if trainer is not None and saved["trainer"] is not None:
                trainer.load_state_dict(saved["trainer"])
            self.reporter.progress("resumed", {"iteration": state.next_iteration,
                                               "training_steps": trainer.steps if trainer else 0})
        elif self.warm is not None:
            from services.solver.optimize.warm_start import apply_warm_start

            state.parameters, self.warm_report = apply_warm_start(spec, self.warm, trainer, prepared.problem,
                                                                  state.parameters, prepared.lower, prepared.upper)
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
                                                  "residual_radiance": stats.radiance_loss,
                                                  "residual_differential": stats.differential_loss})

        # fixed: up to the planned count (a resumed run trains what the uninterrupted one would have);
        # adaptive: until the residual norms say the fields have caught up (training.adaptive_steps)
        stats = trainer.train_iteration(on_step) if adaptive else trainer.train(steps, on_step)
        trainer.check_finite()
        radiance = [s.radiance_loss for s in stats if s.radiance_loss is not None and np.isfinite(s.radiance_loss)]
        differential = [s.differential_loss for s in stats
                        if s.differential_loss is not None and np.isfinite(s.differential_loss)]
        return {"training_steps": len(stats), "residual_radiance": float(np.mean(radiance)) if radiance else None,
                "residual_differential": float(np.mean(differential)) if differential else None}

    def _iteration(self, k: int, prepared: Prepared, built: Built, recipe: Recipe, stream: ViewStream,
                   state: RunState) -> bool:
        """One iteration; returns whether the recipe changed (the plan is then re-reported)."""
        spec, problem, method = self.spec, prepared.problem, built.method
        t0 = time.perf_counter()
        training = self._train(built.trainer, k)
        t1 = time.perf_counter()
        fields = fields_of(built.trainer)
        batch = stream.batch(state.views_offset, recipe.views)
        curvature = state.optimizer.needs_curvature and (state.hessian is None or k % spec.jacobian_every == 0)
        # The successive curvature draws on every view's remembered Jacobians: one new one per
        # iteration keeps the memory fresh (the batch's first view, rotating with the stream)
        measured = set(batch.sensors[:1] if spec.hessian == "successive" else batch.sensors) if curvature else set()
        n = problem.parameters.n
        loss, dz_dp, candidates, jacobians, seeds = 0.0, np.zeros(n), {}, {}, {}
        for sensor in batch.sensors:
            seed = derive_seed(spec.seed, "iteration", k, sensor)
            if sensor not in state.losses:
                state.losses[sensor] = ImageLoss(spec.loss, prepared.targets[sensor], problem.count_sanitized)
            loss_of = state.losses[sensor]

            if sensor in measured and built.jacobian is None:
                candidate, z, g, jacobians[sensor] = method.candidate_gradient_and_images(
                    problem, fields, loss_of, spp=recipe.spp, gradient_spp=recipe.gradient_spp, seed=seed,
                    depth=prepared.depth, sensor=sensor)
            else:
                candidate, z, g = method.candidate_and_gradient(
                    problem, fields, loss_of, spp=recipe.spp, gradient_spp=recipe.gradient_spp, seed=seed,
                    depth=prepared.depth, sensor=sensor)
                if sensor in measured:
                    assert built.jacobian is not None
                    jacobians[sensor] = built.jacobian.images(problem, fields, spp=recipe.gradient_spp,
                                                              seed=derive_seed(seed, "jacobian"), sensor=sensor)
            seeds[sensor] = seed
            dz_dp += batch.scale * g
            loss += batch.scale * z
            candidates[sensor] = candidate
        t2 = time.perf_counter()
        if curvature:
            source = method if built.jacobian is None else built.jacobian
            state.hessian = self._curvature(problem, source, fields, jacobians, seeds, recipe, state,
                                            len(prepared.targets), learning_rate(spec, k))
        lr = learning_rate(spec, k)
        step_gradient = regularized(prepared.textures, spec.textures, dz_dp, state.parameters, k, spec.iterations)
        updated = state.optimizer.step(state.parameters, step_gradient, prepared.lower, prepared.upper, lr=lr,
                                       hessian=state.hessian)
        state.views_offset = batch.offset
        problem.parameters.assign(updated)
        decision = grow_batch(recipe, len(prepared.targets), k) if state.optimizer.noise_dominated() else None
        write = state.images.due(k, spec, asked=self.reporter.images_requested(), elapsed=time.perf_counter() - t0)
        renders = gradients = None
        t3 = time.perf_counter()
        if write:  # at the parameters the record's step was taken at (the images show what it saw)
            problem.parameters.assign(state.parameters)
            renders, gradients = render_views(prepared, method, fields, candidates, k, recipe.spp, recipe.gradient_spp)
            problem.parameters.assign(updated)
        t4 = time.perf_counter()
        state.images.spent(t4 - t3, t4 - t0, written=write)
        if write and prepared.textures:  # each texture and its gradient (a texture too), never P images
            self.reporter.textures(k, prepared.textures.images(state.parameters) | prepared.textures.gradients(dz_dp))
        record = IterationRecord(
            iteration=k, loss=loss, **record_fields(prepared.textures, state.parameters, updated, dz_dp,
                                                    prepared.target_values),
            learning_rate=lr, images=write, sanitized=dict(problem.sanitized),
            views=batch.sensors, optimizer=state.optimizer.describe() or None,
            seconds={"training": t1 - t0, "gradient": t2 - t1, "step": t3 - t2, "images": t4 - t3},
            parameter_error=(float(np.max(np.abs(state.parameters - prepared.target_values)))
                             if prepared.target_values is not None else None),
            **training)
        state.parameters = updated
        self.reporter.iteration(record, renders, gradients)
        return decision is not None

    def _curvature(self, problem, source: GradientMethod, fields, jacobians: dict[int, np.ndarray], seeds: dict,
                   recipe: Recipe, state: RunState, sensors: int, lr: float) -> np.ndarray:
        """The Gauss-Newton curvature ``H`` of the loss summed over every view, from the Jacobians
        ``jacobians`` of this iteration's views (``hessian``):

        ``successive``  each view's two most recent Jacobians *before* this iteration, cross-
                        multiplied (:func:`hessian_of`), summed over the views that have any and
                        scaled to all ``sensors``: independent of this iteration's gradient (which
                        the Jacobian's noise would otherwise correlate with the curvature, biasing
                        the fixed point of ``H⁻¹ g``) and of each other's noise. Only Jacobians
                        taken within :data:`FRESH` learning rates of the current parameters count:
                        while the parameters travel (far from the answer, where the signal beats
                        the noise) the curvature comes from this iteration's own Jacobians.
        ``product``     ``(2/n) JᵀJ`` of this iteration's views, scaled to all views
        ``cross``       this iteration's against a second estimate drawn now
        """
        block = BLOCK if recipe.jacobian == "method" and recipe.method == "prb" else 1
        current = {s: jacobian_matrix(_finite(problem, "Jacobian pixels (non-finite)", j), block)
                   for s, j in jacobians.items()}
        kind, here = self.spec.hessian, state.parameters
        if kind == "cross":
            total = np.zeros((problem.parameters.n, problem.parameters.n))
            for sensor, jac in current.items():
                other = source.images(problem, fields, spp=recipe.gradient_spp, seed=derive_seed(seeds[sensor], "cross"),
                                      sensor=sensor)
                total += hessian_of(jac, jacobian_matrix(_finite(problem, "Jacobian pixels (non-finite)", other), block))
            return total * sensors / len(current)
        fresh = [[jac for at, jac in pairs if np.max(np.abs(at - here)) <= FRESH * lr]
                 for pairs in state.jacobians.values()] if kind == "successive" else []
        remembered = [hessian_of(*jacs[:2]) for jacs in fresh if jacs]
        if remembered:
            hessian = np.sum(remembered, axis=0) * sensors / len(remembered)
        else:  # "product", or nothing fresh to remember
            hessian = np.sum([hessian_of(jac) for jac in current.values()], axis=0) * sensors / len(current)
        if kind == "successive":
            for sensor, jac in current.items():
                state.jacobians[sensor] = [(here.copy(), jac)] + state.jacobians.get(sensor, [])[:1]
        return hessian

    # -------------------------------------------------------------- reports

    def _plan(self, prepared: Prepared, built: Built, recipe: Recipe) -> dict:
        problem, trainer, textures = prepared.problem, built.trainer, prepared.textures
        width, height = problem.scene.resolution()
        return {
            "method": self.method_name,
            "recipe": recipe.to_json(),
            "realised_by": type(built.method).__name__,
            "fields": {"radiance": trainer is not None and trainer.radiance is not None,
                       "differential": trainer is not None and (trainer.differential is not None
                                                                or trainer.head is not None)},
            "scalars": textures.labels,
            "keys": problem.parameters.keys,
            "init": textures.scalars(prepared.init),
            "lower": textures.scalars(prepared.lower),
            "upper": [u if np.isfinite(u) else None for u in textures.scalars(prepared.upper)],
            "target_values": None if prepared.target_values is None else textures.scalars(prepared.target_values),
            "textures": textures.plan(prepared.init, prepared.lower, prepared.upper, prepared.target_values),
            "sensors": sorted(prepared.targets),
            "resolution": [width, height],
            "depths": prepared.depths,
            "prepared_seconds": prepared.seconds,
            "render": self.spec.render.model_dump(mode="json"),
            "training": self.spec.training.model_dump(mode="json"),
            "effects": problem.plan.to_json() if problem.plan is not None else None,
            "iterations": self.spec.iterations,
            "warm_start": self.warm_report,
            "device": describe_device(),
        }

    def _checkpoint(self, state: RunState, recipe: Recipe, trainer: FieldTrainer | None) -> None:
        blob = checkpoint.dumps(spec=self.spec, next_iteration=state.next_iteration, parameters=state.parameters,
                                optimizer=state.optimizer.state_dict(), views_offset=state.views_offset,
                                batch=(recipe.views, recipe.spp, recipe.gradient_spp), hessian=state.hessian,
                                jacobians=state.jacobians,
                                trainer=None if trainer is None else trainer.state_dict(), method=self.method_name)
        self.reporter.checkpoint(blob, state.next_iteration)

    def _outcome(self, status: Outcome, state: RunState | None, started: float, error: str | None = None,
                 field: str | None = None) -> RunOutcome:
        return RunOutcome(status=status, iterations=state.next_iteration if state is not None else 0,
                          seconds=time.perf_counter() - started,
                          parameters=None if state is None else (self.listed.scalars(state.parameters) if self.listed
                                                                 is not None else state.parameters.tolist()),
                          error=error, field=field)


def _finite(problem, what: str, array: np.ndarray) -> np.ndarray:
    """Zero non-finite entries, counted in the job's metrics (never silently)."""
    bad = ~np.isfinite(array)
    if bad.any():
        problem.count_sanitized(what, int(bad.sum()))
        array = np.asarray(np.where(bad, 0.0, array), dtype=array.dtype)
    return array

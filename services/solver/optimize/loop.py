"""The inverse-rendering loop (paper Sec. 5, Fig. 3b), one iteration at a time:

    1. train / fine-tune L_phi and dL_theta for the current parameters      (Eq. 5-9, Sec. 6.1)
    2. render the candidate y of each view of the iteration's batch and     (a mini-batch of views,
       its loss z(y) against the target                                      scaled to the sum)
    3. dz/dy
    4.-5. dz/dp = dz/dy · dy/dp with the recipe's gradient method             (Eq. 3, 10, 11 / Sec. 6.3)
       (``prb`` does 2-5 in one differentiable render), and the Jacobian J = dI/dp of the views
       the optimizer's curvature asks for (:mod:`.estimate`)
    6. a step of the optimizer (Adam, Gauss-Newton, Levenberg-Marquardt; the second-order rules
       update their curvature from J first), projected onto the bounds

A job is resolved once into its :class:`~services.solver.optimize.recipe.Recipe`
(:mod:`.resolve`), whose objects :mod:`.build` makes; the run never decides again what the recipe
decided. What it decides on the way (a larger batch when the steps turn noise-dominated) is an
event appended to the plan. Renders of every view and gradient images are written on a budget
(``images_every`` / ``images_budget``) and when the host asks for them.

The loop computes and reports (:class:`~services.solver.optimize.report.RunReporter`); it never
writes a file or a job record. The CLI, the worker and the tests differ only in their reporter.
"""

from __future__ import annotations

import base64
import logging
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.outcomes import Outcome
from schemas.records import IterationRecord
from services.solver.optimize.answer import Estimate
from services.solver.optimize.background import BackgroundReporter
from services.solver.optimize.build import Built, build
from services.solver.optimize.estimate import BatchEstimate, block_of, estimate_batch
from services.solver.optimize.floor import block_residual
from services.solver.optimize.images import render_views, silhouette_views
from services.solver.optimize.recipe import Decision, Recipe
from services.solver.optimize.regularize import regularized
from services.solver.optimize.remeshing import adopt, remesh_run, topology
from services.solver.optimize.report import RunAborted, RunOutcome, RunReporter, StopReason
from services.solver.optimize.resolve import resolve, undetermined_texels
from services.solver.optimize.setup import Prepared, prepare
from services.solver.optimize.state import RunState, describe, initial_state, restore, save
from services.solver.optimize.textures import TextureReport, record_fields
from services.solver.optimize.views import ViewStream
from services.solver.scene.params import ParameterSet
from services.solver.seeds import derive_seed
from services.solver.training.trainer import FieldTrainer, fields_of

log = logging.getLogger(__name__)

#: Seconds between two warm-up progress reports.
PROGRESS_SECONDS = 2.0


class Stopped(Exception):
    """The host asked the run to stop: ``canceled`` (the job ends) or ``interrupted`` (the run
    checkpoints and the host resumes it later)."""

    def __init__(self, reason: StopReason):
        super().__init__(reason)
        self.reason = reason


def training_steps_by(spec: JobSpec, k: int) -> int:
    """Training steps done by the end of iteration ``k``'s training phase: the warm-up, then
    ``steps_per_iteration`` per iteration. A resumed run trains up to the same count, so it draws
    the samples the uninterrupted run would have drawn."""
    return spec.training.warmup_steps + k * spec.training.steps_per_iteration


class Clock:
    """Seconds per phase of an iteration, in the order the phases ran."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self.last = self.start = time.perf_counter()

    def lap(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self.last
        self.last = now

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.start


def final_textures(textures: TextureReport, state: RunState, undetermined: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A texture job's answer, by name: each texture's estimate (``<key>``), its standard error
    per texel (``<key>.standard_error``: infinite where ``undetermined[key]`` ``(H, W)`` says no
    pixel pins the texel down) and the last iterate (``<key>.last``)."""
    answer = state.answer.estimate()
    out = textures.images(answer.values)
    out |= {f"{key}.last": image for key, image in textures.images(state.parameters).items()}
    if answer.standard_error is not None:
        for key, image in textures.images(answer.standard_error).items():
            if key in undetermined:
                image = np.where(undetermined[key][..., None], np.inf, image).astype(np.float32)
            out[f"{key}.standard_error"] = image
    return out


class InverseRenderingRun:
    """One execution (attempt) of a job.

    ``scene_file``  the staged XML of an uploaded or local scene (None for built-ins)
    ``resume``      the bytes of a checkpoint to continue from
    ``warm``        the checkpoint of ``spec.warm_start``'s job (:mod:`.warm_start`)
    """

    def __init__(self, spec: JobSpec, reporter: RunReporter, *, scene_file: Path | None = None,
                 resume: bytes | None = None, warm: bytes | None = None):
        self.spec = spec
        self.reporter = reporter
        self.scene_file = scene_file
        self.resume = resume
        self.warm = warm
        self.warm_report: dict | None = None
        self.method_name = str(spec.method)  # the method that runs: an auto job's choice once resolved
        self.listed: TextureReport | None = None  # which scalars reports list (textures are summarised)
        self.seconds: dict = {}                   # preparing and deciding (plan.json's prepared_seconds)
        self.parameter_set: ParameterSet | None = None   # the job's parameters once prepared (their poses)
        self._target_silhouettes: dict[int, np.ndarray] = {}   # a geometry job's, by view (computed once)

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
        state: RunState | None = None
        try:
            prepared, measures = prepare(self.spec, scene_file=self.scene_file,
                                         on_phase=lambda what: self.reporter.progress("preparing", {"what": what}))
            self.listed = prepared.textures
            self.parameter_set = prepared.problem.parameters
            recipe = resolve(self.spec, prepared.problem.parameters, len(prepared.targets), measures)
            self.seconds = {**prepared.seconds, "resolve": sum(measures.seconds.values())}
            self.method_name = recipe.method
            built = build(prepared, recipe)
            state = self._initial_state(prepared, recipe, built)
            self._report_plan(prepared, recipe, built, state)
            self.reporter.targets(prepared.targets)
            if prepared.textures.targets(prepared.target_values):   # final/<key>.target, for comparison
                self.reporter.textures(None, prepared.textures.targets(prepared.target_values))
            views = ViewStream(sorted(prepared.targets), derive_seed(self.spec.seed, "batches"))
            while not self._stopped(state) and state.next_iteration < self.spec.iterations:
                self._stop_if_asked()
                self._remesh_if_due(state.next_iteration, prepared, recipe, built, state)
                answer = self._iteration(state.next_iteration, prepared, recipe, built, views, state)
                state.auto_held = state.auto_held + 1 if recipe.stop.auto_holds(answer) else 0
                reason = recipe.stop.reason(answer, state.auto_held)
                if reason is not None or state.next_iteration == self.spec.iterations:
                    k = state.next_iteration - 1
                    state.events.append(Decision("stop", state.next_iteration, reason or (
                        f"the cap of {self.spec.iterations} iterations (the job's iterations)"), k))
                    self._report_plan(prepared, recipe, built, state)
                if state.next_iteration % self.spec.checkpoint_every == 0 or self._stopped(state):
                    self.reporter.checkpoint(self._save(prepared, recipe, built, state), state.next_iteration)
            if prepared.textures:
                undetermined = undetermined_texels(recipe, measures, dict(prepared.problem.parameters.textures))
                self.reporter.textures(None, final_textures(prepared.textures, state, undetermined))
            if isinstance(self.reporter, BackgroundReporter):
                self.reporter.flush()  # success only once every report is written
            return self._outcome(Outcome.SUCCEEDED, state, started)
        except RunAborted:
            raise
        except Stopped as stop:
            log.info("run %s at iteration %s", stop.reason, state.next_iteration if state else 0)
            if stop.reason == Outcome.INTERRUPTED:
                if state is not None:
                    self.reporter.checkpoint(self._save(prepared, recipe, built, state), state.next_iteration)
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

    @staticmethod
    def _stopped(state: RunState) -> bool:
        """Whether the run has ended: a stop decision is its last event (:mod:`.stopping`)."""
        return bool(state.events) and state.events[-1].what == "stop"

    def _stop_if_asked(self) -> None:
        reason = self.reporter.should_stop()
        if reason:
            raise Stopped(reason)

    def _save(self, prepared: Prepared, recipe: Recipe, built: Built, state: RunState) -> bytes:
        return save(self.spec, state, built, recipe.method, meshes=topology(prepared, state))

    def _remesh_if_due(self, k: int, prepared: Prepared, recipe: Recipe, built: Built, state: RunState) -> None:
        """Before iteration ``k``: the recipe's remesh, when one is due (:mod:`.remeshing`)."""
        if recipe.remesh is None or k not in recipe.remesh.at or state.last_remesh >= k:
            return
        self.reporter.progress("remeshing", {"iteration": k})
        state.events.append(remesh_run(k, prepared, recipe, built, state))
        self.listed = prepared.textures
        self._report_plan(prepared, recipe, built, state)

    def _initial_state(self, prepared: Prepared, recipe: Recipe, built: Built) -> RunState:
        state = initial_state(prepared, recipe)
        if self.resume is not None:
            restore(self.spec, self.resume, state, built, remeshed=lambda meshes, first: adopt(
                meshes, state.parameters, prepared, recipe, built, state, first=first))
            self.listed = prepared.textures
            self.reporter.progress("resumed", {"iteration": state.next_iteration,
                                               "training_steps": built.trainer.steps if built.trainer else 0})
        elif self.warm is not None:
            from services.solver.optimize.warm_start import apply_warm_start

            state.parameters, self.warm_report = apply_warm_start(self.spec, self.warm, built.trainer,
                                                                  prepared.problem, state.parameters,
                                                                  prepared.lower, prepared.upper)
        prepared.problem.parameters.assign(state.parameters)
        return state

    def _iteration(self, k: int, prepared: Prepared, recipe: Recipe, built: Built, views: ViewStream,
                   state: RunState) -> Estimate:
        """Sec. 5's steps for iteration ``k`` at ``state.parameters`` (module docstring); returns
        the answer after it."""
        clock = Clock()
        training = self._train(built.trainer, k)
        clock.lap("training")
        batch = views.batch(state.views_offset, state.batch.views)
        estimate = estimate_batch(k, prepared, recipe, built, state, batch, fields_of(built.trainer))
        clock.lap("gradient")
        renders, gradients, silhouettes = self._images(k, prepared, recipe, built, state, estimate, clock)
        lr = recipe.steps.learning_rate_at(k)
        gradient = regularized(prepared.textures, self.spec.textures, estimate.dz_dp, state.parameters, k,
                               self.spec.iterations, dict(recipe.texture_blocks))
        updated = built.optimizer.step(state.parameters, gradient, prepared.lower, prepared.upper, lr=lr,
                                       jacobians=estimate.jacobians)
        refusal = prepared.problem.parameters.refuse(state.parameters, updated)
        if refusal is not None:   # a shape's non-finite vertices or inverted triangles: never written
            log.warning("iteration %d: step refused (%s)", k, refusal)
            prepared.problem.count_refused(refusal)
            built.optimizer.refused()
            updated = np.array(state.parameters, np.float64)
        answer = self._answer(k, prepared, recipe, built, state, estimate)
        clock.lap("step")
        grown = state.batch.grow(recipe.batch, len(prepared.targets), k) if built.optimizer.noise_dominated() else None
        record = self._record(k, prepared, built, state, estimate, answer, updated, lr, training, clock,
                              renders is not None)
        state.images.spent(clock.seconds.get("images", 0.0), clock.elapsed, written=renders is not None)
        self.reporter.iteration(record, renders, gradients, silhouettes)
        state.advance(prepared, updated, batch.offset)
        if grown is not None:
            state.events.append(grown)
            self._report_plan(prepared, recipe, built, state)
        return answer

    def _train(self, trainer: FieldTrainer | None, k: int) -> dict:
        if trainer is None:
            return {}
        adaptive = self.spec.training.adaptive_steps
        planned = training_steps_by(self.spec, k)
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

    def _images(self, k: int, prepared: Prepared, recipe: Recipe, built: Built, state: RunState,
                estimate: BatchEstimate, clock: Clock) -> tuple[dict | None, dict | None, dict | None]:
        """Every view's render and gradient images at the iteration's parameters, when due
        (:class:`~.images.ImageSchedule`), and a geometry job's silhouettes; a texture job's
        textures and their gradient."""
        if not state.images.due(k, self.spec, asked=self.reporter.images_requested(), elapsed=clock.elapsed):
            return None, None, None
        renders, gradients = render_views(prepared, built.method, fields_of(built.trainer), estimate.candidates, k,
                                          state.batch.spp, state.batch.gradient_spp, recipe.depth)
        shapes = prepared.problem.parameters.shape_reports(state.parameters, final=True)
        if shapes:   # each optimized mesh as a PLY snapshot
            self.reporter.meshes(k, {shape: base64.b64decode(report["ply"]) for shape, report in shapes.items()})
        if prepared.textures:  # each texture and its gradient (a texture too), never P images
            self.reporter.textures(k, prepared.textures.images(state.parameters)
                                   | prepared.textures.gradients(estimate.dz_dp))
        silhouettes = None
        if prepared.problem.parameters.has_geometry:
            silhouettes = silhouette_views(prepared, state.parameters, self._target_silhouettes)
        clock.lap("images")
        return renders, gradients, silhouettes

    @staticmethod
    def _answer(k: int, prepared: Prepared, recipe: Recipe, built: Built, state: RunState,
                estimate: BatchEstimate) -> Estimate:
        """The answer after this iteration: its gradient, weighted by its samples (views x samples
        per pixel), joins the estimate, and each view's residual the floor (:mod:`.answer`)."""
        curvature = built.optimizer.curvature
        if curvature is not None:
            block = block_of(recipe)
            for view, candidate in estimate.candidates.items():
                jacobian = estimate.jacobians.get(view)
                loss = state.loss_of(prepared, view, recipe.blur_at(k))   # the residual of its images, as J
                state.answer.residual(k, view, block_residual(loss.image(candidate), loss.target, block),
                                      None if jacobian is None else jacobian[0], state.batch.spp)
        weight = len(estimate.candidates) * state.batch.gradient_spp
        state.answer.observe(state.parameters, estimate.dz_dp, weight, None if curvature is None else curvature.hessian)
        return state.answer.estimate()

    def _record(self, k: int, prepared: Prepared, built: Built, state: RunState, estimate: BatchEstimate,
                answer: Estimate, updated: np.ndarray, lr: float, training: dict, clock: Clock,
                images: bool) -> IterationRecord:
        target, listed = prepared.target_values, prepared.textures
        return IterationRecord(
            iteration=k, loss=estimate.loss,
            **record_fields(prepared.textures, state.parameters, updated, estimate.dz_dp, target),
            learning_rate=lr, images=images, sanitized=dict(prepared.problem.sanitized),
            refused=dict(prepared.problem.refused),
            views=list(estimate.candidates),
            optimizer=built.optimizer.describe() or None,
            seconds={phase: clock.seconds.get(phase, 0.0) for phase in ("training", "gradient", "step", "images")},
            parameter_error=listed.error(state.parameters, target),
            estimate=listed.scalars(answer.values),
            standard_error=None if answer.standard_error is None else listed.scalars(answer.standard_error),
            estimate_window=[answer.start, answer.end],
            estimate_error=listed.error(answer.values, target),
            shapes=prepared.problem.parameters.shape_reports(state.parameters) or None,
            **training)

    # -------------------------------------------------------------- reports

    def _report_plan(self, prepared: Prepared, recipe: Recipe, built: Built, state: RunState) -> None:
        self.reporter.plan(describe(prepared, recipe, built, state, seconds=self.seconds,
                                    warm_start=self.warm_report))

    def _outcome(self, status: Outcome, state: RunState | None, started: float, error: str | None = None,
                 field: str | None = None) -> RunOutcome:
        """How the run ended, with its answer: the estimate and its standard errors, and the last
        iterate under its own name."""
        outcome = RunOutcome(status=status, iterations=state.next_iteration if state is not None else 0,
                             seconds=time.perf_counter() - started, error=error, field=field)
        if state is None:
            return outcome
        listed = self.listed.scalars if self.listed is not None else (lambda v: np.asarray(v).tolist())
        outcome.last_iterate = outcome.parameters = listed(state.parameters)
        if state.next_iteration > 0:
            answer = state.answer.estimate()
            outcome.parameters = listed(answer.values)
            outcome.standard_error = None if answer.standard_error is None else listed(answer.standard_error)
            outcome.estimate = {"kind": answer.kind, "window": [answer.start, answer.end],
                                "run_error": None if answer.run_error is None else listed(answer.run_error),
                                "floor_error": None if answer.floor_error is None else listed(answer.floor_error)}
        if self._stopped(state):
            outcome.stopped = asdict(state.events[-1])
        if self.parameter_set is not None and self.parameter_set.has_geometry:
            answer_values = state.answer.estimate().values if state.next_iteration > 0 else state.parameters
            outcome.poses = self.parameter_set.pose_reports(answer_values) or None
            outcome.meshes = self.parameter_set.shape_reports(answer_values, final=True) or None
        return outcome

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
from services.solver.optimize.answer import Estimate
from services.solver.optimize.background import BackgroundReporter
from services.solver.optimize.estimate import BatchEstimate
from services.solver.optimize.images import render_views, silhouette_views
from services.solver.optimize.plan import describe
from services.solver.optimize.recipe import Decision
from services.solver.optimize.remeshing import remesh_run, resumed
from services.solver.optimize.report import RunAborted, RunOutcome, RunReporter, StopReason
from services.solver.optimize.resolve import resolve, undetermined_texels
from services.solver.optimize.run import Run
from services.solver.optimize.setup import prepare
from services.solver.optimize.state import RunState
from services.solver.optimize.textures import TextureReport
from services.solver.optimize.views import ViewStream
from services.solver.seeds import derive_seed

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
    """One execution (attempt) of a job: its :class:`~.run.Run` driven to the end, with every
    step reported.

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
        self.run: Run | None = None           # once prepared and resolved
        self.seconds: dict = {}               # preparing and deciding (plan.json's prepared_seconds)
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
        try:
            prepared, measures = prepare(self.spec, scene_file=self.scene_file, on_phase=self._preparing)
            recipe = resolve(self.spec, prepared.problem.parameters, len(prepared.targets), measures)
            self.seconds = {**prepared.seconds, "resolve": sum(measures.seconds.values())}
            self.method_name = recipe.method
            self.run = self._started(Run.start(prepared, recipe))
            self._report_plan()
            self.reporter.targets(prepared.targets)
            if prepared.textures.targets(prepared.target_values):   # final/<key>.target, for comparison
                self.reporter.textures(None, prepared.textures.targets(prepared.target_values))
            views = ViewStream(sorted(prepared.targets), derive_seed(self.spec.seed, "batches"))
            while not self._stopped() and self.run.state.next_iteration < self.spec.iterations:
                self._stop_if_asked()
                self._remesh_if_due(self.run.state.next_iteration)
                self._iteration(self.run.state.next_iteration, views)
                if self.run.state.next_iteration % self.spec.checkpoint_every == 0 or self._stopped():
                    self.reporter.checkpoint(self.run.save(), self.run.state.next_iteration)
            if self.run.prepared.textures:
                textures = self.run.prepared.textures
                undetermined = undetermined_texels(recipe, measures, dict(prepared.problem.parameters.textures))
                self.reporter.textures(None, final_textures(textures, self.run.state, undetermined))
            if isinstance(self.reporter, BackgroundReporter):
                self.reporter.flush()  # success only once every report is written
            return self._outcome(Outcome.SUCCEEDED, started)
        except RunAborted:
            raise
        except Stopped as stop:
            log.info("run %s at iteration %s", stop.reason, self.run.state.next_iteration if self.run else 0)
            if stop.reason == Outcome.INTERRUPTED:
                if self.run is not None:
                    self.reporter.checkpoint(self.run.save(), self.run.state.next_iteration)
                return self._outcome(Outcome.INTERRUPTED, started)
            return self._outcome(Outcome.CANCELED, started)
        except InvalidJob as exc:
            return self._outcome(Outcome.FAILED, started, error=str(exc), field=exc.field)
        except FloatingPointError as exc:
            k = self.run.state.next_iteration if self.run else 0
            return self._outcome(Outcome.FAILED, started, error=f"iteration {k}: {exc}")
        except Exception as exc:  # recorded, never silent; the host decides what else to do
            log.exception("run failed")
            return self._outcome(Outcome.FAILED, started, error=f"{type(exc).__name__}: {exc}")

    # -------------------------------------------------------------- phases

    def _preparing(self, what: str) -> None:
        """A phase of the set-up begins: reported, and a cancel asked for is honoured here."""
        self.reporter.progress("preparing", {"what": what})
        self._stop_if_asked()

    def _stopped(self) -> bool:
        """Whether the run has ended: a stop decision is its last event (:mod:`.stopping`)."""
        events = self.run.state.events if self.run is not None else []
        return bool(events) and events[-1].what == "stop"

    def _stop_if_asked(self) -> None:
        reason = self.reporter.should_stop()
        if reason:
            raise Stopped(reason)

    def _remesh_if_due(self, k: int) -> None:
        """Before iteration ``k``: the recipe's remesh, when one is due (:mod:`.remeshing`)."""
        run = self.run
        assert run is not None
        if run.recipe.remesh is None or k not in run.recipe.remesh.at or run.state.last_remesh >= k:
            return
        self.reporter.progress("remeshing", {"iteration": k})
        self.run, event = remesh_run(k, run)
        self.run.state.events.append(event)
        self._report_plan()

    def _started(self, run: Run) -> Run:
        """``run`` resumed from its checkpoint, or warm-started from another job's, or as is."""
        if self.resume is not None:
            run = resumed(run, self.resume)
            self.reporter.progress("resumed", {"iteration": run.state.next_iteration,
                                               "training_steps": run.built.trainer.steps if run.built.trainer else 0})
        elif self.warm is not None:
            from services.solver.optimize.warm_start import apply_warm_start

            prepared = run.prepared
            run.state.parameters, self.warm_report = apply_warm_start(self.spec, self.warm, run.built.trainer,
                                                                      prepared.problem, run.state.parameters,
                                                                      prepared.lower, prepared.upper)
        run.prepared.problem.parameters.assign(run.state.parameters)
        return run

    def _iteration(self, k: int, views: ViewStream) -> None:
        """Sec. 5's steps for iteration ``k`` at the run's parameters (module docstring), then
        the stop rule on the answer after it."""
        run, clock = self.run, Clock()
        assert run is not None
        training = self._train(k)
        clock.lap("training")
        batch = views.batch(run.state.views_offset, run.state.batch.views)
        estimate = run.estimate(k, batch)
        clock.lap("gradient")
        renders, gradients, silhouettes = self._images(k, estimate, clock)
        step = run.step(k, estimate)
        answer = run.answer(k, estimate)
        clock.lap("step")
        grown = run.grown(k)
        record = run.record(k, estimate, step, answer, training=training, seconds=clock.seconds,
                            images=renders is not None)
        run.state.images.spent(clock.seconds.get("images", 0.0), clock.elapsed, written=renders is not None)
        self.reporter.iteration(record, renders, gradients, silhouettes)
        run.state.advance(run.prepared, step.updated, batch.offset)
        if grown is not None:
            run.state.events.append(grown)
            self._report_plan()
        self._stop_if_done(answer)

    def _stop_if_done(self, answer: Estimate) -> None:
        """The recipe's stop rule on the answer after an iteration, or the cap of iterations: the
        ``stop`` event (:mod:`.stopping`)."""
        run = self.run
        assert run is not None
        state, stop = run.state, run.recipe.stop
        state.auto_held = state.auto_held + 1 if stop.auto_holds(answer) else 0
        reason = stop.reason(answer, state.auto_held)
        if reason is not None or state.next_iteration == self.spec.iterations:
            state.events.append(Decision("stop", state.next_iteration, reason or (
                f"the cap of {self.spec.iterations} iterations (the job's iterations)"), state.next_iteration - 1))
            self._report_plan()

    def _train(self, k: int) -> dict:
        trainer = self.run.built.trainer if self.run is not None else None
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

    def _images(self, k: int, estimate: BatchEstimate,
                clock: Clock) -> tuple[dict | None, dict | None, dict | None]:
        """Every view's render and gradient images at the iteration's parameters, when due
        (:class:`~.images.ImageSchedule`), and a geometry job's silhouettes; a texture job's
        textures and their gradient."""
        run = self.run
        assert run is not None
        prepared, state = run.prepared, run.state
        if not state.images.due(k, self.spec, asked=self.reporter.images_requested(), elapsed=clock.elapsed):
            return None, None, None
        renders, gradients = render_views(prepared, run.built.method, run.fields, estimate.candidates, k,
                                          state.batch.spp, state.batch.gradient_spp, run.recipe.depth)
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

    # -------------------------------------------------------------- reports

    def _report_plan(self) -> None:
        assert self.run is not None
        self.reporter.plan(describe(self.run, seconds=self.seconds, warm_start=self.warm_report).model_dump(mode="json"))

    def _outcome(self, status: Outcome, started: float, error: str | None = None,
                 field: str | None = None) -> RunOutcome:
        """How the run ended, with its answer: the estimate and its standard errors, and the last
        iterate under its own name."""
        run = self.run
        outcome = RunOutcome(status=status, iterations=run.state.next_iteration if run is not None else 0,
                             seconds=time.perf_counter() - started, error=error, field=field)
        if run is None:
            return outcome
        state, listed = run.state, run.prepared.textures.scalars
        parameter_set = run.prepared.problem.parameters
        outcome.last_iterate = outcome.estimate = listed(state.parameters)
        if state.next_iteration > 0:
            answer = state.answer.estimate()
            outcome.estimate = listed(answer.values)
            outcome.standard_error = None if answer.standard_error is None else listed(answer.standard_error)
            outcome.estimate_kind, outcome.estimate_window = answer.kind, [answer.start, answer.end]
            outcome.run_error = None if answer.run_error is None else listed(answer.run_error)
            outcome.floor_error = None if answer.floor_error is None else listed(answer.floor_error)
        if self._stopped():
            outcome.stopped = asdict(state.events[-1])
        if parameter_set.has_geometry:
            answer_values = state.answer.estimate().values if state.next_iteration > 0 else state.parameters
            outcome.poses = parameter_set.pose_reports(answer_values) or None
            outcome.meshes = parameter_set.shape_reports(answer_values, final=True) or None
        return outcome

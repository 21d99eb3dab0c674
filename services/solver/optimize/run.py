"""A run's objects in one place, in the manner of nerfstudio's trainer (which holds its pipeline
and optimizers): the job as prepared (:class:`~.setup.Prepared`), the recipe it was resolved into
once (:class:`~.recipe.Recipe`), the objects built from that recipe (:class:`~.build.Built`) and
the state one iteration hands the next (:class:`~.state.RunState`). The phases of Sec. 5 are its
methods; the host-facing loop (:mod:`.loop`) calls them and reports.

A remesh changes the number of scalars ``P``: :func:`.remeshing.remesh_run` returns a new run (new
``(P',)`` arrays, optimizer and answer), and so does a resume from a remeshed checkpoint
(:func:`.remeshing.resumed`). Neither patches the run it starts from, except for the scene
itself, which both share: Mitsuba's mesh is replaced in place.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from schemas.records import IterationRecord
from services.solver.estimators.methods import Fields
from services.solver.optimize.answer import Estimate
from services.solver.optimize.build import Built, build
from services.solver.optimize.estimate import BatchEstimate, block_of, jacobian_of
from services.solver.optimize.floor import block_residual
from services.solver.optimize.recipe import Decision, Recipe
from services.solver.optimize.regularize import regularized
from services.solver.optimize.setup import Prepared
from services.solver.optimize.state import RunState, initial_state, save
from services.solver.optimize.textures import record_fields
from services.solver.optimize.views import Batch
from services.solver.seeds import derive_seed
from services.solver.training.trainer import fields_of

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class Step:
    """An iteration's step of the optimizer: the parameters after it ``(P,)`` (the iteration's own
    when the step was refused) and its learning rate."""

    updated: np.ndarray
    learning_rate: float


@dataclass(frozen=True)
class Run:
    """The run's objects (module docstring). ``state`` changes every iteration
    (:meth:`~.state.RunState.advance`); the others change only by a new :class:`Run`."""

    prepared: Prepared
    recipe: Recipe
    built: Built
    state: RunState

    @classmethod
    def start(cls, prepared: Prepared, recipe: Recipe) -> Run:
        """The run at its first iteration: the recipe's objects, the initial values."""
        built = build(prepared, recipe)
        return cls(prepared, recipe, built, initial_state(prepared, recipe))

    @property
    def fields(self) -> Fields:
        return fields_of(self.built.trainer)

    # -------------------------------------------------------------- Sec. 5, steps 2-6

    def estimate(self, k: int, batch: Batch) -> BatchEstimate:
        """Steps 2-5 for iteration ``k``'s ``batch`` at the scene's current parameters
        (:mod:`.estimate`): each view's candidate and loss, ``dz/dp`` (Eq. 10) scaled to the sum
        over every view, and the Jacobian (Eq. 3) of the views the curvature asks for; every
        ``recipe.bias_every`` iterations also ``prb``'s unbiased ``dz/dp`` of the same views."""
        prepared, recipe, built, state, fields = self.prepared, self.recipe, self.built, self.state, self.fields
        problem, seed0, size = prepared.problem, prepared.spec.seed, state.batch
        measured, draws = built.optimizer.jacobians_wanted(k, batch.sensors)
        block = block_of(recipe)
        out = BatchEstimate(0.0, np.zeros(problem.parameters.n))
        for view in batch.sensors:
            seed = derive_seed(seed0, "iteration", k, view)
            loss = state.loss_of(prepared, view, recipe.blur_at(k))
            images = None
            if view in measured and built.jacobian is None:   # the same samples give J
                candidate, z, dz_dp, images = built.method.candidate_gradient_and_images(
                    problem, fields, loss, spp=size.spp, gradient_spp=size.gradient_spp, seed=seed,
                    depth=recipe.depth, sensor=view)
            else:
                candidate, z, dz_dp = built.method.candidate_and_gradient(
                    problem, fields, loss, spp=size.spp, gradient_spp=size.gradient_spp, seed=seed,
                    depth=recipe.depth, sensor=view)
                if view in measured:   # J from another source (the hybrid's dL_theta): a seed of its own
                    images = built.jacobian_source.gradient_images(problem, fields, spp=size.gradient_spp,
                                                                   seed=derive_seed(seed, "jacobian"), sensor=view)
            if built.check is not None and k % recipe.bias_every == 0:   # prb's unbiased dz/dp, its own samples
                _, _, unbiased = built.check.candidate_and_gradient(
                    problem, fields, loss, spp=size.spp, gradient_spp=size.gradient_spp,
                    seed=derive_seed(seed, "bias"), depth=recipe.depth, sensor=view)
                out.unbiased = batch.scale * unbiased + (0.0 if out.unbiased is None else out.unbiased)
            out.dz_dp += batch.scale * dz_dp
            out.loss += batch.scale * z
            out.candidates[view] = candidate
            if images is not None:   # the Jacobian of the loss's images (a blurred loss's: G J)
                out.jacobians[view] = [jacobian_of(problem, loss.jacobian(images), block)]
                if draws > 1:   # a second independent draw, for the cross curvature
                    other = built.jacobian_source.gradient_images(problem, fields, spp=size.gradient_spp,
                                                                  seed=derive_seed(seed, "cross"), sensor=view)
                    out.jacobians[view].append(jacobian_of(problem, loss.jacobian(other), block))
        return out

    def step(self, k: int, estimate: BatchEstimate) -> Step:
        """Step 6: the optimizer's step from the regularized ``dz/dp``, projected onto the bounds;
        a step the parameters refuse (a shape's non-finite vertices or inverted triangles) is
        never taken."""
        prepared, state, optimizer = self.prepared, self.state, self.built.optimizer
        lr = self.recipe.steps.learning_rate_at(k)
        spec = prepared.spec
        gradient = regularized(prepared.textures, spec.textures, estimate.dz_dp, state.parameters, k,
                               spec.iterations, dict(self.recipe.texture_blocks))
        updated = optimizer.step(state.parameters, gradient, prepared.lower, prepared.upper, lr=lr,
                                 jacobians=estimate.jacobians)
        refusal = prepared.problem.parameters.refuse(state.parameters, updated)
        if refusal is not None:
            log.warning("iteration %d: step refused (%s)", k, refusal)
            prepared.problem.count_refused(refusal)
            optimizer.refused()
            updated = np.array(state.parameters, np.float64)
        return Step(updated, lr)

    def answer(self, k: int, estimate: BatchEstimate) -> Estimate:
        """The answer after iteration ``k``: its gradient, weighted by its samples (views x samples
        per pixel), joins the estimate, and each view's residual the floor (:mod:`.answer`)."""
        prepared, recipe, state = self.prepared, self.recipe, self.state
        curvature = self.built.optimizer.curvature
        if curvature is not None:
            block = block_of(recipe)
            for view, candidate in estimate.candidates.items():
                jacobian = estimate.jacobians.get(view)
                loss = state.loss_of(prepared, view, recipe.blur_at(k))   # the residual of its images, as J
                state.answer.residual(k, view, block_residual(loss.image(candidate), loss.target, block),
                                      None if jacobian is None else jacobian[0], state.batch.spp)
        weight = len(estimate.candidates) * state.batch.gradient_spp
        if estimate.unbiased is not None:
            state.answer.check(k, estimate.unbiased - estimate.dz_dp)
        state.answer.observe(state.parameters, estimate.dz_dp, weight, None if curvature is None else curvature.hessian)
        return state.answer.estimate()

    def grown(self, k: int) -> Decision | None:
        """A larger batch, when the optimizer says its steps are noise-dominated (the recipe's
        ``batch`` rule); None otherwise."""
        if not self.built.optimizer.noise_dominated():
            return None
        return self.state.batch.grow(self.recipe.batch, len(self.prepared.targets), k)

    def record(self, k: int, estimate: BatchEstimate, step: Step, answer: Estimate, *, training: dict,
               seconds: dict[str, float], images: bool) -> IterationRecord:
        """Iteration ``k``'s record: the iterate and its step, the answer after it, the seconds
        per phase and the fields' training."""
        prepared, state = self.prepared, self.state
        target, listed = prepared.target_values, prepared.textures
        return IterationRecord(
            iteration=k, loss=estimate.loss,
            **record_fields(listed, state.parameters, step.updated, estimate.dz_dp, target),
            learning_rate=step.learning_rate, images=images, sanitized=dict(prepared.problem.sanitized),
            refused=dict(prepared.problem.refused), views=list(estimate.candidates),
            optimizer=self.built.optimizer.describe() or None,
            seconds={phase: seconds.get(phase, 0.0) for phase in ("training", "gradient", "step", "images")},
            parameter_error=listed.error(state.parameters, target),
            estimate=listed.scalars(answer.values),
            standard_error=None if answer.standard_error is None else listed.scalars(answer.standard_error),
            estimate_window=[answer.start, answer.end],
            estimate_error=listed.error(answer.values, target),
            shapes=prepared.problem.parameters.shape_reports(state.parameters) or None,
            **training)

    # -------------------------------------------------------------- checkpoints

    def save(self) -> bytes:
        """The checkpoint of this run (:func:`~.state.save`), with a remeshed mesh's triangles."""
        return save(self.prepared.spec, self.state, self.built, self.recipe.method, meshes=self.topology())

    def topology(self) -> dict[str, dict[str, np.ndarray]] | None:
        """What a checkpoint keeps of the remeshed meshes (:mod:`.remeshing`): each one's vertices
        as remeshed and its faces, by shape id; None when the run has not remeshed."""
        if not any(event.what == "remesh" for event in self.state.events):
            return None
        return {shape: {"vertices": mesh.v0, "faces": mesh.faces}
                for shape, mesh in self.prepared.problem.parameters.shapes.items()}

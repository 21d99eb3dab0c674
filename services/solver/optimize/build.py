"""The objects of a run, built from its recipe (nerfstudio's config-to-object pattern): the
problem narrowed to the recipe's effects, the gradient method, the trainer of exactly the fields
it uses, the source of the second-order steps' Jacobian, and the optimizer. Nothing is decided
here: every choice is the recipe's (:mod:`.resolve`), and this module reads nothing else of the
job than its seed and the settings it passes on unread (the training's, ``render.freeze``).

The cached camera first hits serve the recipe's ``candidate = "field"`` and ``first_hits =
"cached"``; with ``jacobian: "differential-field"``, ``dL_theta`` queried at cached first hits is
the Jacobian of the second-order steps whatever the gradient method (with ``prb``: the hybrid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.solver.estimators.methods import GradientMethod, make_method
from services.solver.estimators.methods.prb import Prb, channel_groups
from services.solver.fields.field import NeuralField
from services.solver.optimize.optimizers import ParameterOptimizer, make_optimizer
from services.solver.optimize.optimizers.adam import Adam
from services.solver.optimize.recipe import Recipe
from services.solver.optimize.setup import Prepared
from services.solver.training.trainer import FieldTrainer


@dataclass
class Built:
    method: GradientMethod              # candidate and dz/dp
    trainer: FieldTrainer | None        # the fields, when the method or the Jacobian uses them
    jacobian: GradientMethod | None     # the Jacobian's source when it is not the method itself
    optimizer: ParameterOptimizer
    check: GradientMethod | None = None  # prb, whose unbiased dz/dp checks a biased method's (recipe.bias_every)

    @property
    def jacobian_source(self) -> GradientMethod:
        return self.method if self.jacobian is None else self.jacobian


def apply_effects(prepared: Prepared, recipe: Recipe) -> None:
    """Narrow the prepared problem to what the recipe simulates: its effects and its layout."""
    problem = prepared.problem
    if recipe.effects is not None:
        problem.simulate(recipe.effects)
    problem.layout = recipe.layout


def build(prepared: Prepared, recipe: Recipe) -> Built:
    """The run's objects (module docstring)."""
    spec, problem = prepared.spec, prepared.problem
    apply_effects(prepared, recipe)
    method = make_method(recipe.method, problem.effects, recipe.depth)
    if isinstance(method, Prb):
        method.freeze = spec.render.freeze
        method.fit_views(len(prepared.targets), len(channel_groups(list(problem.layout.channels))))
    if recipe.head:  # the many-parameter head (checked by the validate stage: ndrf-rhs, first order)
        from services.solver.estimators.methods.head import NdrfHead

        method = NdrfHead()
    hybrid = recipe.hybrid
    field_user = make_method(recipe.fields_for, problem.effects, recipe.depth) if hybrid and recipe.fields_for else method
    trainer = None
    if recipe.radiance or recipe.differential:
        trainer = FieldTrainer(problem, spec.training, radiance=recipe.radiance, differential=recipe.differential,
                               seed=spec.seed)
    jacobian_method = None
    if hybrid:
        jacobian_method = _cached(prepared, recipe, field_user, trainer, field_candidate=False, cached_lhs=True)
    if recipe.candidate == "field" or recipe.first_hits == "cached":
        method = _cached(prepared, recipe, method, trainer, field_candidate=recipe.candidate == "field",
                         cached_lhs=recipe.first_hits == "cached")
    check = make_method("prb", problem.effects, recipe.depth) if recipe.bias_every else None
    return Built(method, trainer, jacobian_method, build_optimizer(prepared, recipe), check)


def build_optimizer(prepared: Prepared, recipe: Recipe) -> ParameterOptimizer:
    """The recipe's update rule over the parameters as they are now: its steps measured in the
    scalars' units and Adam's shared scales over each mesh's span, by the rules the recipe's
    ``step_units`` and ``uniform`` record for the scalars as loaded (after a remesh the new
    vertices have other spans, :mod:`.remeshing`)."""
    steps, parameters = recipe.steps, prepared.problem.parameters
    optimizer = make_optimizer(steps.optimizer, parameters.n, lr=steps.learning_rate, betas=steps.betas,
                               damping=steps.damping, trust_growth=steps.trust_growth, trust_start=steps.trust_start,
                               curvature=steps.curvature, curvature_every=steps.curvature_every,
                               views=len(prepared.targets))
    if recipe.step_units:
        optimizer.units = np.asarray(parameters.step_units(), np.float64)
    if recipe.uniform and isinstance(optimizer, Adam):
        optimizer.uniform = tuple(parameters.shape_spans())
    return optimizer


def _cached(prepared: Prepared, recipe: Recipe, method: GradientMethod, trainer: FieldTrainer | None, *,
            field_candidate: bool, cached_lhs: bool) -> GradientMethod:
    """The method on camera first hits traced once per job."""
    from services.solver.estimators.first_hits import FirstHitCache
    from services.solver.estimators.methods.cached import CachedFirstHits

    spec = prepared.spec
    fields = [f for f in trainer.fields().values() if isinstance(f, NeuralField)] if trainer is not None else []
    cache = FirstHitCache(prepared.problem, sorted(prepared.targets), recipe.cache_spp, spec.seed, fields)
    return CachedFirstHits(method, cache, field_candidate=field_candidate, cached_lhs=cached_lhs)


"""A gradient method, the source of its Jacobian and the trainer of their fields, built the way a
run uses them.

One place for what the loop needs: the effect plan for the method, the method shaped by it
(``make_method``), the trainer of exactly the fields it uses (``trainer_for``), the cached camera
first hits when the job asks for them (``render.candidate = "field"`` or ``render.first_hits =
"cached"``), and, for ``jacobian: "differential-field"``, ``dL_theta`` queried at cached first hits
as the Jacobian of the second-order steps whatever the gradient method (with ``prb``: the hybrid).
"""

from __future__ import annotations

from dataclasses import dataclass

from schemas.methods import Method
from services.solver.estimators.methods import GradientMethod, make_method
from services.solver.estimators.methods.prb import Prb, channel_groups
from services.solver.fields.field import NeuralField
from services.solver.optimize.setup import Prepared, plan_for
from services.solver.training.trainer import FieldTrainer, trainer_for


@dataclass
class Built:
    method: GradientMethod              # candidate and dz/dp
    trainer: FieldTrainer | None        # the fields, when the method or the Jacobian uses them
    jacobian: GradientMethod | None     # the Jacobian's source when it is not the method itself


def build(prepared: Prepared, name: str, jacobian: str = "method") -> Built:
    """The method ``name`` on the prepared problem (re-planned for it), its Jacobian source and the
    trainer of the fields they use (None when they use none)."""
    spec = prepared.spec
    hybrid = jacobian == "differential-field" and name != Method.NDRF_LHS
    plan_for(prepared, str(Method.NDRF_LHS) if hybrid else name, jacobian)
    method = make_method(name, prepared.problem.plan, prepared.depth)
    if isinstance(method, Prb):
        method.freeze = spec.render.freeze
        method.fit_views(len(prepared.targets), len(channel_groups(list(prepared.problem.layout.channels))))
    if spec.training.head is not None:  # the many-parameter head (checked by setup.check: ndrf-rhs, first order)
        from services.solver.estimators.methods.head import NdrfHead

        method = NdrfHead()
    render = spec.render
    field_user = make_method(Method.NDRF_LHS, prepared.problem.plan, prepared.depth) if hybrid else method
    trainer = trainer_for(prepared.problem, field_user, spec.training, spec.seed, radiance=render.candidate == "field")
    if hybrid and trainer is not None and trainer.differential is None:
        raise ValueError("jacobian 'differential-field' needs dL_theta, and the effect plan turned it off")
    jacobian_method = None
    if hybrid:
        jacobian_method = _cached(prepared, field_user, trainer, field_candidate=False, cached_lhs=True)
    elif jacobian == "differential-field":  # ndrf-lhs: its own images are dL_theta, at cached hits
        render = render.model_copy(update={"first_hits": "cached"})
    if render.candidate == "field" or render.first_hits == "cached":
        method = _cached(prepared, method, trainer, field_candidate=render.candidate == "field",
                         cached_lhs=render.first_hits == "cached")
    return Built(method, trainer, jacobian_method)


def _cached(prepared: Prepared, method: GradientMethod, trainer: FieldTrainer | None, *, field_candidate: bool,
            cached_lhs: bool) -> GradientMethod:
    """The method on camera first hits traced once per job."""
    from services.solver.estimators.first_hits import FirstHitCache
    from services.solver.estimators.methods.cached import CachedFirstHits

    spec = prepared.spec
    fields = [f for f in trainer.fields().values() if isinstance(f, NeuralField)] if trainer is not None else []
    cache = FirstHitCache(prepared.problem, sorted(prepared.targets), spec.render.gradient_spp, spec.seed, fields)
    return CachedFirstHits(method, cache, field_candidate=field_candidate, cached_lhs=cached_lhs)

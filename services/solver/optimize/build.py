"""A gradient method and the trainer of its fields, built the way a run uses them.

One place for what the loop and ``auto``'s trial both need: the effect plan for the method, the
method shaped by it (``make_method``), the trainer of exactly the fields it uses
(``trainer_for``), and the cached camera first hits when the job asks for them
(``render.candidate = "field"`` or ``render.first_hits = "cached"``).
"""

from __future__ import annotations

from services.solver.estimators.methods import GradientMethod, make_method
from services.solver.estimators.training import FieldTrainer, trainer_for
from services.solver.optimize.setup import Prepared, plan_for


def build(prepared: Prepared, name: str) -> tuple[GradientMethod, FieldTrainer | None]:
    """The method ``name`` on the prepared problem (re-planned for it) and its trainer (None when
    it uses no field)."""
    spec = prepared.spec
    plan_for(prepared, name)
    method = make_method(name, prepared.problem.plan, prepared.depths["render"])
    render = spec.render
    trainer = trainer_for(prepared.problem, method, spec.training, spec.seed, radiance=render.candidate == "field")
    if render.candidate == "field" or render.first_hits == "cached":
        method = _cached(prepared, method, trainer)
    return method, trainer


def _cached(prepared: Prepared, method: GradientMethod, trainer: FieldTrainer | None) -> GradientMethod:
    """The method on camera first hits traced once per job (``render.candidate`` / ``first_hits``)."""
    from services.solver.estimators.first_hits import FirstHitCache
    from services.solver.estimators.methods.cached import CachedFirstHits

    spec = prepared.spec
    fields = list(trainer.fields().values()) if trainer is not None else []
    cache = FirstHitCache(prepared.problem, sorted(prepared.targets), spec.render.gradient_spp, spec.seed, fields)
    return CachedFirstHits(method, cache, field_candidate=spec.render.candidate == "field",
                           cached_lhs=spec.render.first_hits == "cached")

"""The registry of gradient methods, by their public names, and how an effect plan shapes them."""

from __future__ import annotations

from services.estimators.gradients import Direct, GradientMethod, NdrfLhs, NdrfRhs, RadianceCache
from services.estimators.reference import Prb
from services.scene.planner import EffectPlan

METHODS: dict[str, type[GradientMethod]] = {cls.name: cls for cls in (NdrfLhs, NdrfRhs, RadianceCache, Direct, Prb)}


def make_method(name: str, *, max_depth: int = 12, plan: EffectPlan | None = None) -> GradientMethod:
    """Instantiate a method by name (``prb`` takes the reference path depth).

    With a plan, a method uses only the fields the plan trains: without ``dL_theta`` (no
    interreflection, or forced off) ``ndrf-lhs`` and ``ndrf-rhs`` estimate ``∂L_r`` by one bounce
    (exact without interreflection); without ``L_phi`` the ``(∂f) L`` term sees emission only.
    """
    if name not in METHODS:
        raise ValueError(f"unknown gradient method {name!r}; known: {', '.join(METHODS)}")
    if name == "prb":
        return Prb(max_depth=max_depth)
    if plan is None:
        return METHODS[name]()
    radiance, differential = bool(plan.radiance_field.value), bool(plan.differential_field.value)
    if name == "ndrf-lhs":
        return NdrfLhs() if differential else NdrfRhs(radiance, False)
    if name == "ndrf-rhs":
        return NdrfRhs(radiance, differential)
    if name == "radiance-cache":
        return RadianceCache(radiance)
    return Direct()

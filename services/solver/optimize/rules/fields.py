"""The fields a run trains, the effects they simulate, and where the Jacobian comes from.

Rules: the fields serve the resolved method (or ``ndrf-lhs``, whose ``dL_theta`` is the Jacobian
of another method: the hybrid), and the effects are chosen for it from the effect probe
(:func:`services.solver.scene.effects.choose_effects`); none for geometry, none per scalar under
the many-parameter head (which simulates every effect). Where the scene turns ``dL_theta`` off
(no light bounces between surfaces), a job's ``jacobian: "differential-field"`` is moot: the
method's own Jacobian, with the reason. ``dL_theta``'s Jacobian is read at the camera's first
hits, traced once per job (``first_hits: "cached"``).
"""

from __future__ import annotations

from schemas.job import JobSpec
from schemas.methods import Method
from services.solver.estimators.methods import make_method, method_class
from services.solver.estimators.render import PathDepth
from services.solver.optimize.recipe import Recipe
from services.solver.optimize.rules.inputs import Decide, Measures, Parameters
from services.solver.scene.effects import Effects, choose_effects
from services.solver.training.trainer import trained_fields


def fields_method(spec: JobSpec, method: str) -> str | None:
    """The method whose fields the run trains, which the effects are chosen for: ``method`` (the
    resolved one), or ``ndrf-lhs`` when its ``dL_theta`` is the Jacobian of another method (the
    hybrid); None when no field is trained (``prb``, ``direct``) or the many-parameter head
    simulates every effect (no per-scalar choice of P scalars)."""
    if spec.training.head is not None:
        return None
    if spec.jacobian == "differential-field":
        return str(Method.NDRF_LHS)
    return method if method_class(method).uses else None


def _planned(spec: JobSpec, method: str, parameters: Parameters, measures: Measures) -> tuple[str | None,
                                                                                              Effects | None]:
    """The method the fields serve (:func:`fields_method`; none for geometry) and the effects
    chosen for it from the effect probe (None without a field)."""
    planned_for = fields_method(spec, method) if not parameters.has_geometry else None
    if planned_for is None:
        return None, None
    return planned_for, choose_effects(measures.facts(), planned_for, method_class(planned_for).uses, spec.effects,
                                       spec.training.delta_depth)


def planned_fields(spec: JobSpec, method: str, parameters: Parameters, measures: Measures,
                   decide: Decide) -> tuple[JobSpec, str | None, Effects | None]:
    """The method the fields serve and their effects (module docstring), and ``spec`` with its
    ``jacobian`` as resolved: ``method`` where the scene needs no ``dL_theta``."""
    planned_for, effects = _planned(spec, method, parameters, measures)
    if spec.jacobian == "differential-field" and effects is not None and not effects.differential_field.value:
        decide("jacobian", "method", f"jacobian 'differential-field' reads dL_theta, which this scene does not need "
                                     f"({effects.differential_field.reason}): the second-order steps take the "
                                     f"method's own Jacobian")
        spec = spec.model_copy(update={"jacobian": "method"})
        planned_for, effects = _planned(spec, method, parameters, measures)
    return spec, planned_for, effects


def trained(spec: JobSpec, planned_for: str | None, effects: Effects | None, depth: PathDepth) -> tuple[bool, bool]:
    """The fields the run trains, ``(L_phi, dL_theta)``: those of the method they serve, as the
    effects shape it (:func:`services.solver.training.trainer.trained_fields`); both for the
    many-parameter head; ``L_phi`` too when the candidate is the field's."""
    field_candidate = spec.render.candidate == "field"
    if spec.training.head is not None:
        return True, True
    if planned_for is None:
        return field_candidate, False
    radiance, differential = trained_fields(make_method(planned_for, effects, depth), effects, radiance=field_candidate)
    return radiance, differential


def first_hits(spec: JobSpec, method: str, planned_for: str | None, decide: Decide) -> str:
    """Where the camera's first hits come from: the job's ``render.first_hits``, ``cached`` where
    the Jacobian is ``dL_theta`` at them and the fields serve the method itself (not the hybrid)."""
    hits = spec.render.first_hits
    if spec.jacobian == "differential-field" and hits != "cached" and not Recipe.is_hybrid(method, planned_for):
        hits = "cached"
        decide("first_hits", hits, "the Jacobian is dL_theta at the camera's first hits, traced once per job")
    return hits

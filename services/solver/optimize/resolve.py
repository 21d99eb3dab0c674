"""A job resolved into its recipe, once: :func:`resolve` turns a validated job into a frozen
:class:`~services.solver.optimize.recipe.Recipe`, every choice with the reason a user reads in
``plan.json``. Nothing downstream decides again: :mod:`.build` makes the run's objects from the
recipe, and what the run itself decides on the way (a larger batch, a stop) is appended to the
plan as an event.

Pure: the scene enters only through :class:`~.rules.inputs.Measures`, measurements taken when
(and only when) a rule needs them. The rules, each a module of :mod:`.rules` with its constants,
its reason and the benchmark it rests on, in the order :func:`resolve` applies them:

* the gradient method: ``auto``'s for scalars (:mod:`.rules.method`: ``prb``, or ``ndrf-lhs``
  in a closed scene whose run pays for the warm-up) or for geometry (:mod:`.rules.geometry`: a
  projective integrator);
* the path depth and what a truncated one misses (:mod:`.rules.depth`);
* the fields, their effects and the Jacobian's source (:mod:`.rules.fields`), the derivatives
  carried (:mod:`.rules.layout`) and a pose's step units (:mod:`.rules.geometry`);
* the optimizer (:mod:`.rules.optimizer`; a mesh's: :mod:`.rules.geometry`) and
  Levenberg-Marquardt's trust region (:mod:`.rules.trust_region`);
* the first batch of views and samples (:mod:`.rules.batch`, :mod:`.rules.first_spp`);
* a geometry job's blur (:mod:`.blur`), remeshing and curvature (:mod:`.rules.geometry`);
* the stop (:mod:`.stopping`), the check of a biased gradient (:mod:`.rules.bias`) and a
  texture's resolution (:mod:`.rules.texture_resolution`).
"""

from __future__ import annotations

from schemas.job import JobSpec
from schemas.methods import AUTO
from services.solver.optimize.blur import resolve_blur
from services.solver.optimize.recipe import Decision, Recipe, Steps
from services.solver.optimize.rules.batch import GEOMETRY_SPP, MAX_GROWTH, TEXTURE_SPP, batch
from services.solver.optimize.rules.bias import BIAS_EVERY, BIASED_GRADIENTS, bias_check
from services.solver.optimize.rules.depth import MISSING_ENERGY, path_depth
from services.solver.optimize.rules.fields import fields_method, first_hits, planned_fields, trained
from services.solver.optimize.rules.first_spp import INDIRECT_SPP
from services.solver.optimize.rules.geometry import (
    DIRECT_DEPTH,
    curvature,
    flat_shading_warning,
    geometry_method,
    remesh_schedule,
    shape_optimizer,
    step_units,
)
from services.solver.optimize.rules.inputs import Measures, Parameters
from services.solver.optimize.rules.layout import derivative_layout, jacobian_renders
from services.solver.optimize.rules.method import NDRF_MAX_SCALARS, NDRF_MIN_WORK, auto_method
from services.solver.optimize.rules.optimizer import MAX_GEOMETRY_RENDERS, MAX_JACOBIAN_RENDERS, PATH_METHODS, optimizer
from services.solver.optimize.rules.texture_resolution import (
    MAX_BLOCK,
    PIXELS_PER_TEXEL,
    texture_blocks,
    undetermined_texels,
)
from services.solver.optimize.rules.trust_region import (
    CLOSED,
    CLOSED_GROWTH,
    CLOSED_START,
    OPEN_GROWTH,
    OPEN_START,
    trust_region,
)
from services.solver.optimize.stopping import stop_rule

#: What callers import from here: :func:`resolve`, its inputs, what the run derives again after a
#: remesh, and the rules' constants (each defined in its rule's module).
__all__ = [
    "BIAS_EVERY", "BIASED_GRADIENTS", "CLOSED", "CLOSED_GROWTH", "CLOSED_START", "DIRECT_DEPTH", "GEOMETRY_SPP",
    "INDIRECT_SPP", "MAX_BLOCK", "MAX_GEOMETRY_RENDERS", "MAX_GROWTH", "MAX_JACOBIAN_RENDERS", "MISSING_ENERGY",
    "NDRF_MAX_SCALARS", "NDRF_MIN_WORK", "OPEN_GROWTH", "OPEN_START", "PATH_METHODS", "PIXELS_PER_TEXEL",
    "TEXTURE_SPP", "Measures", "Parameters", "derivative_layout", "fields_method", "jacobian_renders", "resolve",
    "undetermined_texels",
]


def resolve(spec: JobSpec, parameters: Parameters, sensors: int, measures: Measures) -> Recipe:
    """Everything the run of ``spec`` will do (module docstring): ``parameters`` are the job's
    optimized scalars, ``sensors`` its target views; ``measures`` is asked only for what a rule
    needs."""
    decisions: list[Decision] = []

    def decide(what: str, value: str | int | float, reason: str) -> None:
        decisions.append(Decision(what, value, reason))

    if parameters.has_geometry:
        method = geometry_method(spec, measures, decide)
    else:
        method = auto_method(spec, parameters, measures, decide) if spec.method == AUTO else str(spec.method)
    depth, warnings = path_depth(spec, measures, decide)
    if parameters.has_geometry and (flat := flat_shading_warning(parameters.flat_meshes())) is not None:
        warnings.append(flat)
    spec, planned_for, effects = planned_fields(spec, method, parameters, measures, decide)
    if effects is not None:
        warnings += effects.warnings
    layout = derivative_layout(parameters, effects, spec.effects.merge_channels)
    units = step_units(parameters, decide)
    spans = tuple(parameters.shape_spans()) if parameters.has_geometry else ()
    chosen = shape_optimizer(spec, spans, decide) if spans else optimizer(spec, method, parameters, layout, decide)
    pose = parameters.has_geometry and sum(parameters.geometry) > sum(b - a for a, b in spans)
    growth, start = CLOSED_GROWTH, CLOSED_START
    if chosen == "levenberg-marquardt":
        growth, start = trust_region(measures, decide)
    first = batch(spec, method, chosen, parameters, effects, layout, sensors, measures, decide)
    blur = resolve_blur(spec, pose=pose, shape=bool(spans), film=lambda: measures.film(), decide=decide)
    remesh = remesh_schedule(spec, decide) if spans else None
    steps = Steps(optimizer=chosen, learning_rate=spec.learning_rate,
                  final_learning_rate_ratio=spec.final_learning_rate_ratio, iterations=spec.iterations,
                  betas=spec.adam_betas, damping=spec.damping,
                  curvature=curvature(spec, chosen, blur is not None and pose, decide),
                  curvature_every=spec.jacobian_every, trust_growth=growth, trust_start=start,
                  restarts=remesh.at if remesh is not None else ())
    stop = stop_rule(spec, chosen, decide, not_before=remesh.at[-1] if remesh is not None else 0)
    bias_every = bias_check(spec, method, steps, parameters, decide)
    blocks = texture_blocks(spec, parameters, measures, decide) if parameters.has_textures else ()
    radiance, differential = trained(spec, planned_for, effects, depth)
    hits = first_hits(spec, method, planned_for, decide)
    return Recipe(candidate=spec.render.candidate, first_hits=hits, cache_spp=spec.render.gradient_spp,
                  head=spec.training.head is not None, bias_every=bias_every,
                  method=method, jacobian=spec.jacobian, fields_for=planned_for, depth=depth, effects=effects,
                  layout=layout, steps=steps, batch=first, stop=stop, decisions=tuple(decisions),
                  warnings=tuple(warnings), texture_blocks=blocks, radiance=radiance, differential=differential,
                  step_units=units, uniform=spans if chosen == "adam" else (), blur=blur, remesh=remesh)

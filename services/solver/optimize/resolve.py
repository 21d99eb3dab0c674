"""A job resolved into its recipe, once: :func:`resolve` turns a validated job into a frozen
:class:`~services.solver.optimize.recipe.Recipe`, every choice with the reason a user reads in
``plan.json``. Nothing downstream decides again: :mod:`.build` makes the run's objects from the
recipe, and what the run itself decides on the way (a larger batch, a stop) is appended to the
plan as an event.

Pure: the scene enters only through :class:`Measures`, three measurements taken when (and only
when) a rule needs them: the effect probe (the fields' effects), the scene's closure
(Levenberg-Marquardt's trust region) and whether each scalar is seen directly (``prb``'s first
samples per pixel). The rules and what they rest on (``bench/results/``):

* **prb with Russian roulette** gives an unbiased gradient at the price of one render; with 1
  spp and one view per iteration it is the fastest hand-written Mitsuba loop in every scene
  measured, so it is the gradient of ``auto`` in open scenes.
* **ndrf-lhs in a closed scene** (closure at least :data:`CLOSED`, scalars only, at most
  :data:`NDRF_MAX_SCALARS`, an ``l2`` loss that Levenberg-Marquardt steps on, a run of at least
  :data:`NDRF_MIN_WORK` pixel-iterations that pays for the warm-up): a prb render costs
  more with every bounce and its forward-mode Jacobian is noise at 1 spp, while an NDRF iteration
  costs the same at any depth and its Jacobian is ``dL_theta`` at the camera hits (the candidate
  stays path-traced, so the answer is where the path-traced images match). ``python -m
  bench.pareto --jobs room-closed-8 --variant prb`` measures it at equal seconds.
* **Levenberg-Marquardt** reaches the answer in a few steps where Adam is limited to the
  learning rate per step, when its Jacobian is cheap: a forward-mode render per group of
  scalars that change distinct RGB channels. ``auto`` takes it when the loss is ``l2`` and
  at most :data:`MAX_JACOBIAN_RENDERS` renders per view measure the Jacobian; otherwise Adam.
* **Levenberg-Marquardt's trust region starts at 4 learning rates and grows by 2 on agreeing
  steps where at least 1 - :data:`CLOSED` of the light reflected leaves the scene** (the
  closure, :func:`services.solver.scene.closure.closure`); otherwise it starts at one and grows
  by 3/2: an image's response to an albedo curves like ``a / (1 - a c)``, and Gauss-Newton's
  linear model holds over long steps only where ``c`` is small (``python -m bench.investigations.trust_growth``).
* **One view per iteration at 1 spp**, the batch doubled by the run itself when the steps keep
  reversing (noise-dominated): views while there are more, then samples per pixel; kept as it is
  under Adam, whose moments average the noise.
* **8 samples per pixel from the start where no optimized scalar is seen directly**
  (``python -m bench.investigations.first_spp``): the gradient of a scalar seen only through interreflection is
  the noisy tail of longer paths.
* **A texture** (``bench/results/textures*.md``): Adam (a Gauss-Newton step would need a P x P
  curvature), every view at :data:`TEXTURE_SPP` spp per iteration.
* **A biased gradient is checked** (:data:`BIASED_GRADIENTS`: ``ndrf-rhs``'s or a radiance
  cache's ``dz/dp``): under second-order steps every :data:`BIAS_EVERY` iterations ``prb``'s unbiased
  ``dz/dp`` of the same views is taken too, and the answer's Newton estimate is corrected by the
  mean difference (:mod:`.answer`), its error included; without it, ``ndrf-rhs`` on hidden-object
  as written returned errors 1.5 times its standard errors (``python -m bench.coverage``).
* **Geometry** (a pose, :mod:`services.solver.scene.geometry`): only Mitsuba's projective
  integrators differentiate a moving silhouette; every other method refuses it with the reason.
  ``auto`` takes ``direct-projective`` where direct light is all but :data:`MISSING_ENERGY` of the
  image (measured, :func:`~services.solver.estimators.render.missing_energy`), else
  ``prb-projective``; Levenberg-Marquardt while its Jacobian costs at most
  :data:`MAX_GEOMETRY_RENDERS` forward renders per view (one per pose scalar), every view at
  :data:`GEOMETRY_SPP` spp per iteration (the boundary term at 1 spp is noise; Mitsuba's pose
  tutorial renders 16), and steps measured in the shape's size (:meth:`ParameterSet.step_units
  <services.solver.scene.params.ParameterSet.step_units>`: a degree is not a scene unit).
* **A shape** (a mesh's vertices in LargeSteps coordinates, :mod:`services.solver.scene.shape`):
  the same methods, views and samples; Adam with one step scale per mesh (``uniform``, as
  Mitsuba's shape tutorial): its ``3 N`` scalars would take one forward render each for a
  Jacobian, and per-entry scales would undo the parameterization's smoothing. The job's remeshing
  schedule (``geometry.remesh_at``) cuts the run into stages, each with its own learning-rate
  decay, and no stopping rule ends the run before its last stage.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Protocol

import numpy as np

from schemas.job import JobSpec
from schemas.methods import AUTO, Method
from services.solver.estimators.layout import DerivativeLayout
from services.solver.estimators.methods import make_method, method_class
from services.solver.estimators.methods.prb import channel_groups
from services.solver.estimators.render import PathDepth
from services.solver.optimize.blur import resolve_blur
from services.solver.optimize.recipe import BatchRule, Decision, Recipe, Steps
from services.solver.optimize.resolve_geometry import (
    curvature,
    flat_shading_warning,
    geometry_method,
    remesh_schedule,
    shape_optimizer,
)
from services.solver.optimize.stopping import stop_rule
from services.solver.scene.effects import Effects, choose_effects
from services.solver.scene.facts import SceneFacts
from services.solver.scene.footprint import pixels_per_texel
from services.solver.training.trainer import trained_fields

#: A texture needs this many pixels per texel (median over its footprint) to be optimized at its own resolution.
PIXELS_PER_TEXEL = 4
#: The largest block of texels a texture's resolution is matched with.
MAX_BLOCK = 16
#: A truncated path depth that misses more than this share of the light is a warning in the plan.
MISSING_ENERGY = 1e-3
#: ``auto`` takes Levenberg-Marquardt when its Jacobian costs at most this many forward renders per view.
MAX_JACOBIAN_RENDERS = 4
#: A growing batch stops at this many times its first size (views x samples per pixel).
MAX_GROWTH = 16
#: A scene whose closure (the share of reflected light that hits another surface) is at least this
#: is closed: its images curve strongly in the albedos, and the trust region grows slowly.
CLOSED = 0.95
#: Levenberg-Marquardt's trust-radius growth in an open scene and in a closed one.
OPEN_GROWTH, CLOSED_GROWTH = 2.0, 1.5
#: Its first radius, in learning rates, in an open scene and in a closed one.
OPEN_START, CLOSED_START = 4.0, 1.0
#: Samples per pixel of a texture job whose job leaves them unset.
TEXTURE_SPP = 16
#: Samples per pixel of ``prb``'s first batch when no optimized scalar is seen directly.
INDIRECT_SPP = 8
#: Samples per pixel of a geometry job whose job leaves them unset (Mitsuba's pose tutorial's).
GEOMETRY_SPP = 16
#: ``auto`` takes Levenberg-Marquardt on geometry while its Jacobian costs at most this many forward
#: renders per view (two shapes' poses).
MAX_GEOMETRY_RENDERS = 12
#: The path depth of direct illumination (emitters seen and one bounce), what ``direct-projective`` renders.
DIRECT_DEPTH = PathDepth(2, None)
#: ``auto`` trains a field (``ndrf-lhs``) in a closed scene for at most this many scalars (its
#: ``dL_theta`` has an output per scalar and channel; the closed rooms measured have six).
NDRF_MAX_SCALARS = 12
#: ... and a job of at least this many pixel-iterations (the smallest target view's pixels times the
#: iterations). prb in a closed scene costs about 140 us per pixel-iteration on 2 CPU cores, batch
#: growth and Jacobian renders included (bench/results/pareto.md: 75 s for 30 x 128², 16 s for 30 x
#: 64²), the field's warm-up 20-40 s: below this (about 37 s of prb) the warm-up does not pay.
NDRF_MIN_WORK = 1 << 18
#: The methods whose biased ``dz/dp`` (a learned field's) is checked against ``prb``'s unbiased one
#: every :data:`BIAS_EVERY` iterations. Not ``ndrf-lhs``: in closed rooms, where it is chosen, the
#: checks' 1-spp prb noise moved its answer off (room-closed-8 at 30 iterations, 5 seeds: median max
#: error 0.013 checked, 0.0016 unchecked, on a 2-core AMD EPYC), though bright-room's coverage rose 30% -> 57%.
BIASED_GRADIENTS = (Method.NDRF_RHS, Method.RADIANCE_CACHE)
#: One ``prb`` adjoint render per view of every this many iterations: ten in the window of a
#: 30-iteration run (its last two thirds), at half a prb run's renders.
BIAS_EVERY = 2
#: The methods whose paths are Mitsuba's (forward-mode Jacobian renders, one per channel group).
PATH_METHODS = (Method.PRB, Method.PRB_PROJECTIVE, Method.DIRECT_PROJECTIVE)


class Measures(Protocol):
    """The measurements of the scene :func:`resolve` may ask for, each at the initial values."""

    def facts(self) -> SceneFacts:
        """The effect probe (:func:`services.solver.scene.facts.probe_scene`)."""

    def closure(self) -> float | None:
        """The share of reflected light that hits another surface; None without a reflecting surface."""

    def direct(self) -> list[bool]:
        """Per scalar: whether it changes the light of the camera hits directly."""

    def missing_energy(self, depth: PathDepth) -> float:
        """The share of the image's light a truncated path ``depth`` misses."""

    def footprint(self, key: str, shape: tuple[int, ...]) -> np.ndarray:
        """``(H, W)`` pixels of the target views that see each texel of the texture ``key`` directly."""

    def film(self) -> tuple[int, int]:
        """The smallest target view's ``(width, height)`` in pixels."""


class Parameters(Protocol):
    """What :func:`resolve` reads of the optimized parameters (a ``ParameterSet``)."""

    @property
    def n(self) -> int: ...

    @property
    def has_textures(self) -> bool: ...

    @property
    def has_geometry(self) -> bool: ...

    @property
    def geometry(self) -> list[bool]:
        """Per scalar: whether it moves a shape."""

    def step_units(self) -> np.ndarray:
        """Per scalar: one unit of the optimizer's steps, in the scalar's own units."""

    def shape_spans(self) -> list[tuple[int, int]]:
        """``(start, stop)`` of each shape parameter (a mesh's vertices) in ``p``."""

    def flat_meshes(self) -> list[str]:
        """The posed or reshaped meshes without vertex normals."""

    @property
    def sizes(self) -> list[int]: ...

    @property
    def textures(self) -> list[tuple[str, tuple[int, ...]]]:
        """``(key, (H, W, C))`` of each texture parameter."""


def _auto_method(spec: JobSpec, parameters: Parameters, measures: Measures, decide) -> str:
    """``auto``'s gradient method for scalars (module docstring): ``ndrf-lhs`` in a closed scene
    whose run pays for the warm-up, when Levenberg-Marquardt will take the steps; else ``prb``."""
    eligible = (spec.optimizer in ("auto", "levenberg-marquardt") and spec.loss == "l2" and spec.jacobian == "method"
                and spec.training.head is None and not parameters.has_textures and parameters.n <= NDRF_MAX_SCALARS)
    closure = measures.closure() if eligible else None
    why = ""
    if closure is not None:
        share = f"{closure:.0%} of the light a surface reflects hits another surface"
        if closure < CLOSED:
            why = f"{share} (an open scene: short paths, where a prb iteration is cheaper than training a field); "
        else:
            width, height = measures.film()
            work = width * height * spec.iterations
            size = f"{work / 2**10:.0f} Ki pixel-iterations ({NDRF_MIN_WORK / 2**10:g} Ki pay for the warm-up)"
            if work >= NDRF_MIN_WORK:
                decide("method", str(Method.NDRF_LHS),
                       f"{share} (a closed scene) and {size}: light paths are long, a prb render costs more with "
                       f"every bounce and its forward-mode Jacobian is noisy, while an NDRF iteration costs the same "
                       f"at any depth and its Jacobian is a smooth field query; at equal seconds its answer was "
                       f"better on room-closed-8 (bench/results/pareto-ndrf.md)")
                return str(Method.NDRF_LHS)
            why = f"{share} (a closed scene), but only {size}: the field's warm-up would cost more than it saves; "
    decide("method", str(Method.PRB), f"prb: {why}an unbiased gradient for one adjoint render per view, whatever the "
                                      f"number of scalars; no field to train before the first step")
    return str(Method.PRB)


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


def resolve(spec: JobSpec, parameters: Parameters, sensors: int, measures: Measures) -> Recipe:
    """Everything the run of ``spec`` will do (module docstring): ``parameters`` are the job's
    optimized scalars, ``sensors`` its target views; ``measures`` is asked only for what a rule
    needs."""
    decisions: list[Decision] = []

    def decide(what: str, value, reason: str) -> None:
        decisions.append(Decision(what, value, reason))

    depth = PathDepth(spec.render.max_depth, spec.render.rr_depth)
    if parameters.has_geometry:
        method = geometry_method(spec, measures, decide, direct=DIRECT_DEPTH, limit=MISSING_ENERGY)
    else:
        method = _auto_method(spec, parameters, measures, decide) if spec.method == AUTO else str(spec.method)
    decide("depth", depth.describe(),
           "the job's render.max_depth / rr_depth" if spec.render.max_depth or spec.render.rr_depth != 5
           else "Mitsuba's default: every bounce, so photographs and candidates agree (no depth bias)")
    warnings = []
    if not depth.unbiased:
        missing = measures.missing_energy(depth)
        if missing > MISSING_ENERGY:
            warnings.append(f"render.max_depth {depth.max_depth} misses {missing:.1%} of the image's light at the "
                            f"initial values (more where materials are brighter): the recovered parameters are "
                            f"biased; leave render.max_depth unset for unbounded paths with Russian roulette")
    if parameters.has_geometry and (flat := flat_shading_warning(parameters.flat_meshes())) is not None:
        warnings.append(flat)
    planned_for, effects = _planned(spec, method, parameters, measures)
    if spec.jacobian == "differential-field" and effects is not None and not effects.differential_field.value:
        decide("jacobian", "method", f"jacobian 'differential-field' reads dL_theta, which this scene does not need "
                                     f"({effects.differential_field.reason}): the second-order steps take the "
                                     f"method's own Jacobian")
        spec = spec.model_copy(update={"jacobian": "method"})
        planned_for, effects = _planned(spec, method, parameters, measures)
    if effects is not None:
        warnings += effects.warnings
    layout = derivative_layout(parameters, effects, spec.effects.merge_channels)
    units = tuple(float(u) for u in parameters.step_units()) if parameters.has_geometry else ()
    if any(u != 1.0 for u in units):
        decide("step_units", ", ".join(f"{u:.4g}" for u in sorted(set(units))),
               "a pose's steps are measured in its shape's size: a translation in the shape's radius, a rotation in "
               "radians (which move its farthest vertex by one radius), so that the learning rate and the trust "
               "region mean the same share of the shape for both (degrees are not scene units)")
    spans = tuple(parameters.shape_spans()) if parameters.has_geometry else ()
    optimizer = shape_optimizer(spec, spans, decide) if spans else _optimizer(spec, method, parameters, layout,
                                                                                decide)
    pose = parameters.has_geometry and sum(parameters.geometry) > sum(b - a for a, b in spans)
    growth, start = CLOSED_GROWTH, CLOSED_START
    if optimizer == "levenberg-marquardt":
        growth, start = _trust_region(measures, decide)
    batch = _batch(spec, method, optimizer, parameters, effects, layout, sensors, measures, decide)
    blur = resolve_blur(spec, pose=pose, shape=bool(spans), film=lambda: measures.film(), decide=decide)
    remesh = remesh_schedule(spec, decide) if spans else None
    steps = Steps(optimizer=optimizer, learning_rate=spec.learning_rate,
                  final_learning_rate_ratio=spec.final_learning_rate_ratio, iterations=spec.iterations,
                  betas=spec.adam_betas, damping=spec.damping,
                  curvature=curvature(spec, optimizer, blur is not None and pose, decide),
                  curvature_every=spec.jacobian_every, trust_growth=growth, trust_start=start,
                  restarts=remesh.at if remesh is not None else ())
    stop = stop_rule(spec, optimizer, decide, not_before=remesh.at[-1] if remesh is not None else 0)
    bias_every = _bias_check(spec, method, steps, parameters, decide)
    blocks = _texture_blocks(spec, parameters, measures, decide) if parameters.has_textures else ()
    radiance, differential = _fields(spec, method, planned_for, effects, depth)
    first_hits = spec.render.first_hits
    if spec.jacobian == "differential-field" and first_hits != "cached" and not Recipe.is_hybrid(method, planned_for):
        first_hits = "cached"
        decide("first_hits", first_hits, "the Jacobian is dL_theta at the camera's first hits, traced once per job")
    return Recipe(candidate=spec.render.candidate, first_hits=first_hits, cache_spp=spec.render.gradient_spp,
                  head=spec.training.head is not None, bias_every=bias_every,
                  method=method, jacobian=spec.jacobian, fields_for=planned_for, depth=depth, effects=effects,
                  layout=layout, steps=steps, batch=batch, stop=stop, decisions=tuple(decisions),
                  warnings=tuple(warnings), texture_blocks=blocks, radiance=radiance, differential=differential,
                  step_units=units, uniform=spans if optimizer == "adam" else (), blur=blur, remesh=remesh)


def _fields(spec: JobSpec, method: str, planned_for: str | None, effects: Effects | None,
            depth: PathDepth) -> tuple[bool, bool]:
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


def _bias_check(spec: JobSpec, method: str, steps: Steps, parameters: Parameters, decide) -> int:
    """Every how many iterations ``prb``'s unbiased ``dz/dp`` checks a biased method's (module
    docstring; 0: never): for second-order steps on scalars with a field's or one bounce's gradient."""
    if method not in BIASED_GRADIENTS or not steps.second_order or spec.training.head is not None \
            or parameters.has_textures or parameters.has_geometry:
        return 0
    decide("bias_every", BIAS_EVERY,
           f"{method}'s dz/dp is biased by what its fields miss, which no standard error of its own "
           f"noise holds; every {BIAS_EVERY} iterations prb's unbiased dz/dp of the same views measures that bias, "
           f"and the answer's Newton estimate is corrected by it, its error included (hidden-object as written, "
           f"bench.coverage)")
    return BIAS_EVERY


def _planned(spec: JobSpec, method: str, parameters: Parameters, measures: Measures) -> tuple[str | None,
                                                                                              Effects | None]:
    """The method the fields serve (:func:`fields_method`; none for geometry) and the effects
    chosen for it from the effect probe (None without a field)."""
    planned_for = fields_method(spec, method) if not parameters.has_geometry else None
    if planned_for is None:
        return None, None
    return planned_for, choose_effects(measures.facts(), planned_for, method_class(planned_for).uses, spec.effects,
                                       spec.training.delta_depth)


def undetermined_texels(recipe: Recipe, measures: Measures,
                        shapes: dict[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """Per texture (``shapes``: key -> ``(H, W, C)``), ``(H, W)`` true where the texel's block at
    the recipe's resolution is seen by less than one pixel: the images do not determine it (its
    standard error is infinite)."""
    out = {}
    for key, block in recipe.texture_blocks:
        counts = measures.footprint(key, shapes[key])
        height, width = counts.shape
        rows, columns = -(-height // block), -(-width // block)
        padded = np.zeros((rows * block, columns * block))
        padded[:height, :width] = counts
        sums = padded.reshape(rows, block, columns, block).sum((1, 3))
        out[key] = np.repeat(np.repeat(sums < 1.0, block, axis=0), block, axis=1)[:height, :width]
    return out


def _texture_blocks(spec: JobSpec, parameters: Parameters, measures: Measures, decide) -> tuple[tuple[str, int], ...]:
    """Each texture's block side: 1 (its own resolution), or, with ``textures.resolution`` "auto"
    and fewer than :data:`PIXELS_PER_TEXEL` pixels per texel in its footprint, the smallest power
    of two whose blocks that many pixels each see (at most :data:`MAX_BLOCK`)."""
    out = []
    for key, shape in parameters.textures:
        counts = measures.footprint(key, shape)
        per_texel = pixels_per_texel(counts)
        seen = (f"its footprint: {int(counts.sum())} pixels of the target views see its {shape[0]}x{shape[1]} "
                f"texels directly ({counts.sum() / counts.size:.2g} per texel; {per_texel:.2g} per texel seen, median)")
        if spec.textures.resolution == "full" or per_texel >= PIXELS_PER_TEXEL or not counts.any():
            why = ("the job's textures.resolution 'full'" if spec.textures.resolution == "full" else
                   "no pixel sees it directly (a texture lit or seen through interreflection): nothing to match"
                   if not counts.any() else f"enough pixels for every texel (at least {PIXELS_PER_TEXEL})")
            decide(f"resolution {key}", f"{shape[0]}x{shape[1]}", f"{seen}: {why}")
            out.append((key, 1))
            continue
        block = 2
        while block < MAX_BLOCK and pixels_per_texel(counts, block) < PIXELS_PER_TEXEL:
            block *= 2
        decide(f"resolution {key}", f"{-(-shape[0] // block)}x{-(-shape[1] // block)}",
               f"{seen}: the images cannot pin down its texels (fewer than {PIXELS_PER_TEXEL} pixels per texel), so "
               f"blocks of {block}x{block} texels move together, each seen by {pixels_per_texel(counts, block):.2g} "
               f"pixels (median; textures.resolution 'full' keeps every texel free; bench.investigations.texture_footprint)")
        out.append((key, block))
    return tuple(out)


def derivative_layout(parameters: Parameters, effects: Effects | None, merge_channels: bool) -> DerivativeLayout:
    """The derivatives the run carries: the effects' active scalars and channels, else every scalar
    (each RGB component its own channel, or all three with ``merge_channels`` off)."""
    if effects is not None:
        active = effects.active_channels()
        return DerivativeLayout(tuple(i for i, _ in active), tuple(channels for _, channels in active))
    if not merge_channels:
        return DerivativeLayout.full(parameters.n)
    layout = DerivativeLayout.by_component(list(parameters.sizes))
    if parameters.has_geometry:   # a pose's three scalars are not RGB components: each changes every channel
        moves = parameters.geometry
        layout = DerivativeLayout(layout.scalars, tuple((0, 1, 2) if moves[i] else c
                                                        for i, c in zip(layout.scalars, layout.channels)))
    return layout


def jacobian_renders(layout: DerivativeLayout) -> int:
    """Forward-mode renders per view that measure ``prb``'s Jacobian (one per channel group)."""
    return len(channel_groups(list(layout.channels)))


def _optimizer(spec: JobSpec, method: str, parameters: Parameters, layout: DerivativeLayout, decide) -> str:
    if spec.optimizer != "auto":
        return spec.optimizer
    if spec.loss != "l2":
        decide("optimizer", "adam", f"the {spec.loss} loss has no Gauss-Newton model")
    elif layout.active == 0:
        decide("optimizer", "adam", "no scalar changes the image: nothing to model")
    elif spec.training.head is not None:
        decide("optimizer", "adam", "training.head (the many-parameter head): a Gauss-Newton step would need P "
                                    "Jacobian images per view (services.solver.optimize.validate)")
    elif parameters.has_textures:
        decide("optimizer", "adam", f"a texture's {parameters.n} scalars: a Gauss-Newton step would solve with a "
                                    f"P x P curvature (services.solver.optimize.validate)")
    else:
        renders = jacobian_renders(layout) if method in PATH_METHODS and spec.jacobian == "method" else 0
        cap = MAX_GEOMETRY_RENDERS if parameters.has_geometry else MAX_JACOBIAN_RENDERS
        if parameters.has_geometry and renders <= cap:
            decide("optimizer", "levenberg-marquardt",
                   f"geometry: {renders} forward render(s) per view measure the Jacobian (one per pose scalar, at "
                   f"most {cap}); a pose is a handful of scalars whose image responds smoothly away from the "
                   f"silhouettes, where Gauss-Newton steps in a trust region tell good steps from bad ones")
            return "levenberg-marquardt"
        if renders > cap:
            decide("optimizer", "adam", f"the Jacobian would cost {renders} forward renders per view (more than "
                                        f"{cap}): Adam on the adjoint gradient")
            return "adam"
        cost = (f"{renders} forward render(s) per view measure the Jacobian ({layout.active} scalars in {renders} "
                f"channel group(s))" if renders else "the Jacobian is a field query")
        decide("optimizer", "levenberg-marquardt", f"{cost}: Gauss-Newton steps in a trust region reach the answer "
                                                   f"in fewer iterations than Adam's learning-rate-limited steps")
        return "levenberg-marquardt"
    return "adam"


def _trust_region(measures: Measures, decide) -> tuple[float, float]:
    """Levenberg-Marquardt's growth of the trust radius and its first radius, from the closure."""
    closure = measures.closure()
    if closure is None:
        why = "no reflecting surface to measure the scene's closure on"
        decide("trust_growth", CLOSED_GROWTH, f"{why}: the cautious growth of the trust region (3/2)")
        decide("trust_start", CLOSED_START, f"{why}: the cautious first step, one learning rate (Adam's)")
        return CLOSED_GROWTH, CLOSED_START
    share = f"{closure:.0%} of the light a surface reflects hits another surface"
    if closure < CLOSED:
        decide("trust_growth", OPEN_GROWTH, f"{share}: the images are close to linear in the scalars, and the trust "
                                            f"region doubles on steps that agree")
        decide("trust_start", OPEN_START, f"the same linearity: the first step may be {OPEN_START:g} learning rates "
                                          f"long")
        return OPEN_GROWTH, OPEN_START
    decide("trust_growth", CLOSED_GROWTH, f"{share} (a closed scene): the images curve strongly in the albedos, and "
                                          f"the trust region grows by 3/2 on steps that agree")
    decide("trust_start", CLOSED_START, "the same curvature: the first step is one learning rate long (Adam's)")
    return CLOSED_GROWTH, CLOSED_START


def _batch(spec: JobSpec, method: str, optimizer: str, parameters: Parameters, effects: Effects | None,
           layout: DerivativeLayout, sensors: int, measures: Measures, decide) -> BatchRule:
    """The first batch of views and samples per pixel, and whether the run may grow it."""
    render, auto_views = spec.render, spec.views_per_iteration == "auto"
    unset = not {"spp", "gradient_spp"} & render.model_fields_set
    views = 1 if auto_views else min(int(spec.views_per_iteration), sensors)
    spp, gradient_spp, grows = render.spp, render.gradient_spp, False
    if parameters.has_geometry and auto_views:
        views = sensors
        decide("views", sensors, "geometry: every view per iteration (a silhouette seen from one side leaves the "
                                 "pose's other directions free, and the boundary term is noisy)")
        if unset:
            spp = gradient_spp = GEOMETRY_SPP
            decide("spp", GEOMETRY_SPP, f"geometry: {GEOMETRY_SPP} samples per pixel (the boundary term of a "
                                        f"silhouette at 1 sample per pixel is noise; render.spp and gradient_spp "
                                        f"left unset)")
        return BatchRule(views, spp, gradient_spp, grows=optimizer != "adam", max_growth=MAX_GROWTH)
    if parameters.has_textures and auto_views:
        views = sensors
        decide("views", sensors, "a texture: every view per iteration (each texel is seen by few pixels; one view at "
                                 "a time leaves Adam's steps noise-dominated, bench/results/textures*.md)")
        if unset:
            spp = gradient_spp = TEXTURE_SPP
            decide("spp", TEXTURE_SPP, f"a texture: {TEXTURE_SPP} samples per pixel (render.spp and gradient_spp "
                                       f"left unset)")
        return BatchRule(views, spp, gradient_spp, grows=False, max_growth=MAX_GROWTH)
    if auto_views:
        grows = optimizer != "adam"
        start = (f"one of the {sensors} views per iteration (the fastest hand-written loop's batch too)"
                 if sensors > 1 else "the job's one view")
        decide("views", views, start + ("; the batch doubles whenever the steps turn noise-dominated: views first, "
                                        f"then samples per pixel (up to {MAX_GROWTH}x)" if grows
                                        else "; Adam's moments average the noise"))
    if method == Method.PRB and unset and not parameters.has_textures and _indirect_only(effects, layout, measures):
        spp = gradient_spp = INDIRECT_SPP
        decide("spp", INDIRECT_SPP, f"no optimized scalar is seen directly: its gradient comes from paths of two "
                                    f"bounces or more, whose noise at 1 sample per pixel decides the steps' direction; "
                                    f"{INDIRECT_SPP} samples per pixel from the first iteration "
                                    f"(bench.investigations.first_spp)")
    elif render.spp == 1 and render.gradient_spp == 1:
        decide("spp", 1, "1 sample per pixel: the fastest to a given error in every scene measured; the optimizer "
                         "averages the noise across iterations")
    return BatchRule(views, spp, gradient_spp, grows=grows, max_growth=MAX_GROWTH)


def _indirect_only(effects: Effects | None, layout: DerivativeLayout, measures: Measures) -> bool:
    """True when no active scalar changes the light of the camera hits directly (the hidden
    object of the paper's Fig. 5): from the effects where the method chose them, else measured."""
    if effects is not None:
        active = [s for s in effects.scalars if s.active]
        return bool(active) and all(s.first_bounce is not None and s.first_bounce > 0 for s in active)
    reach: Sequence[bool] = measures.direct()
    seen = [reach[i] for i in layout.scalars]
    return bool(seen) and not any(seen)

"""The recipe a run follows: method, optimizer, Jacobian source, views per iteration, samples and
path depth, each with the reason a user reads in ``plan.json``.

A job may leave every choice to the product (the defaults: ``method``, ``optimizer`` and
``views_per_iteration`` ``"auto"``). No trial is run before the first iteration: the choices
below are made from what the scene and the job show (the effect plan, the losses, the number of
views), and the run's own iterations take the rest (the batch grows when the steps turn
noise-dominated, :func:`grow_batch`). Every decision, at the start or on the way, is a
:class:`Decision` in the plan.

What the rules rest on (``bench/results/mitsuba-loop.md``, ``bench/results/regime-*.md``):

* **prb with Russian roulette** gives an unbiased gradient at the price of one render; with 1
  spp and one view per iteration it is the fastest hand-written Mitsuba loop in every scene
  measured, so it is the gradient of ``auto``.
* **Levenberg-Marquardt** reaches the answer in a few steps where Adam is limited to the
  learning rate per step, when its Jacobian is cheap: a forward-mode render per group of
  scalars that change distinct RGB channels. ``auto`` takes it when the loss is ``l2`` and
  at most :data:`MAX_JACOBIAN_RENDERS` renders per view measure the Jacobian; otherwise Adam.
* **Levenberg-Marquardt's trust region starts at 4 learning rates and grows by 2 on agreeing
  steps where at least 1 - :data:`CLOSED` of the light reflected leaves the scene** (``closure``,
  measured by :func:`services.solver.scene.closure.closure`); otherwise it starts at one and grows
  by 3/2: an image's response to an albedo curves like ``a / (1 - a c)``, and Gauss-Newton's
  linear model holds over long steps only where ``c`` is small (``python -m bench.trust_growth``,
  3 seeds each, iterations to max error 0.02: ``bench/results/trust_growth.md``).
* **One view per iteration at 1 spp**, the batch doubled by the run itself when the steps keep
  reversing (noise-dominated): views while there are more, then samples per
  pixel; kept as it is under Adam, whose moments average the noise.
* **8 samples per pixel from the start where no optimized scalar is seen directly**
  (:func:`indirect_only`; ``python -m bench.first_spp``): the gradient of a scalar seen only
  through interreflection is the noisy tail of longer paths. On hidden-object, 1 spp reached max
  error 0.02 within the job's 30 iterations for 1 seed of 3; 8 spp for all 3, in fewer seconds.
  Where a scalar is seen directly (the demo, the rooms), 1 spp stays fastest.
* **A texture** (``bench/results/textures*.md``): Adam (a Gauss-Newton step would need a P x P
  curvature), every view at :data:`TEXTURE_SPP` spp per iteration (:func:`texture_batch`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass, field

from schemas.job import JobSpec
from schemas.methods import AUTO, Method
from services.solver.estimators.methods.prb import channel_groups
from services.solver.estimators.problem import Problem
from services.solver.estimators.render import PathDepth

#: ``auto`` takes Levenberg-Marquardt when its Jacobian costs at most this many forward renders per view.
MAX_JACOBIAN_RENDERS = 4
#: A growing batch stops at this many times its first size (views x samples per pixel): past it, an
#: iteration would cost more than the averaging over iterations that the learning rate's decay gives.
MAX_GROWTH = 16
#: A scene whose closure (the share of reflected light that hits another surface) is at least this
#: is closed: its images curve strongly in the albedos, and the trust region grows slowly.
CLOSED = 0.95
#: Levenberg-Marquardt's trust-radius growth in an open scene and in a closed one.
OPEN_GROWTH, CLOSED_GROWTH = 2.0, 1.5
#: Its first radius, in learning rates, in an open scene and in a closed one.
OPEN_START, CLOSED_START = 4.0, 1.0
#: Samples per pixel of a texture job whose job leaves them unset (:func:`texture_batch`).
TEXTURE_SPP = 16
#: Samples per pixel of ``prb``'s first batch when no optimized scalar is seen directly
#: (:func:`first_spp`).
INDIRECT_SPP = 8


@dataclass(frozen=True)
class Decision:
    what: str           # "method", "optimizer", "jacobian", "views", "spp", "depth", ...
    value: str | int
    reason: str
    iteration: int | None = None  # None: decided before the first iteration


@dataclass
class Recipe:
    method: str
    optimizer: str
    jacobian: str              # "method" | "differential-field"
    views: int                 # views per iteration now
    adaptive_views: bool       # the batch may grow (views_per_iteration "auto"): views, then spp
    depth: PathDepth
    spp: int                   # samples per pixel of the candidate now
    gradient_spp: int          # samples per pixel of the gradient and the Jacobian now
    first_size: int = 1        # views x gradient spp of the first batch
    trust_growth: float = CLOSED_GROWTH  # Levenberg-Marquardt's trust-radius growth
    trust_start: float = CLOSED_START    # and its first radius, in learning rates
    decisions: list[Decision] = field(default_factory=list)

    def decide(self, what: str, value, reason: str, iteration: int | None = None) -> Decision:
        decision = Decision(what, value, reason, iteration)
        self.decisions.append(decision)
        return decision

    def to_json(self) -> dict:
        return {"method": self.method, "optimizer": self.optimizer, "jacobian": self.jacobian, "views": self.views,
                "spp": self.spp, "gradient_spp": self.gradient_spp, "adaptive_views": self.adaptive_views,
                "depth": self.depth.describe(), "trust_growth": self.trust_growth, "trust_start": self.trust_start,
                "decisions": [asdict(d) for d in self.decisions]}


def jacobian_renders(problem: Problem) -> int:
    """Forward-mode renders per view that measure ``prb``'s Jacobian (one per channel group)."""
    return len(channel_groups(list(problem.layout.channels)))


def depth_of(spec: JobSpec) -> PathDepth:
    return PathDepth(spec.render.max_depth, spec.render.rr_depth)


def choose_recipe(spec: JobSpec, problem: Problem, sensors: int,
                  closure: Callable[[], float | None] | None = None,
                  direct: Callable[[], list[bool]] | None = None) -> Recipe:
    """The recipe before the first iteration (module docstring). Pure: the scene enters only
    through the effect plan already applied to ``problem`` and two measurements, each called only
    when the recipe needs it: ``closure``, the scene's closure (Levenberg-Marquardt's growth; None:
    not measured, the cautious growth) and ``direct``, whether each scalar changes the light of
    the camera hits directly (``prb``'s first samples per pixel; None: not measured, 1 spp)."""
    depth = depth_of(spec)
    method = str(Method.PRB) if spec.method == AUTO else str(spec.method)
    views = 1 if spec.views_per_iteration == "auto" else min(int(spec.views_per_iteration), sensors)
    recipe = Recipe(method, "adam", spec.jacobian, views, spec.views_per_iteration == "auto", depth,
                    spec.render.spp, spec.render.gradient_spp, views * spec.render.gradient_spp)
    if spec.method == AUTO:
        recipe.decide("method", method, "prb: an unbiased gradient for one adjoint render per view, whatever the "
                                        "number of scalars; no field to train before the first step")
    recipe.decide("depth", depth.describe(),
                  "the job's render.max_depth / rr_depth" if spec.render.max_depth or spec.render.rr_depth != 5
                  else "Mitsuba's default: every bounce, so photographs and candidates agree (no depth bias)")
    if spec.optimizer != "auto":
        recipe.optimizer = spec.optimizer
    elif spec.loss != "l2":
        recipe.decide("optimizer", "adam", f"the {spec.loss} loss has no Gauss-Newton model")
    elif problem.layout.active == 0:
        recipe.decide("optimizer", "adam", "no scalar changes the image: nothing to model")
    elif spec.training.head is not None:
        recipe.decide("optimizer", "adam", "training.head (the many-parameter head): a Gauss-Newton step would need "
                                           "P Jacobian images per view (services.solver.optimize.carry)")
    elif problem.parameters.has_textures:
        recipe.decide("optimizer", "adam", f"a texture's {problem.parameters.n} scalars: a Gauss-Newton step would "
                                           f"solve with a P x P curvature (services.solver.optimize.carry)")
    else:
        renders = jacobian_renders(problem) if method == Method.PRB and spec.jacobian == "method" else 0
        if renders <= MAX_JACOBIAN_RENDERS:
            recipe.optimizer = "levenberg-marquardt"
            cost = (f"{renders} forward render(s) per view measure the Jacobian ({problem.layout.active} scalars in "
                    f"{renders} channel group(s))" if renders else "the Jacobian is a field query")
            recipe.decide("optimizer", recipe.optimizer, f"{cost}: Gauss-Newton steps in a trust region reach the "
                                                         f"answer in fewer iterations than Adam's learning-rate-"
                                                         f"limited steps")
        else:
            recipe.decide("optimizer", "adam", f"the Jacobian would cost {renders} forward renders per view "
                                               f"(more than {MAX_JACOBIAN_RENDERS}): Adam on the adjoint gradient")
    if recipe.optimizer == "levenberg-marquardt":
        _trust_growth(recipe, closure)
    if spec.views_per_iteration == "auto" and not problem.parameters.has_textures:
        grows = recipe.optimizer != "adam"
        start = (f"one of the {sensors} views per iteration (the fastest hand-written loop's batch too)"
                 if sensors > 1 else "the job's one view")
        recipe.decide("views", views, start + ("; the batch doubles whenever the steps turn noise-dominated: views "
                                               f"first, then samples per pixel (up to {MAX_GROWTH}x)"
                                               if grows else "; Adam's moments average the noise"))
        recipe.adaptive_views = grows
    if problem.parameters.has_textures and spec.views_per_iteration == "auto":
        texture_batch(spec, recipe, sensors)
    elif (method == Method.PRB and not problem.parameters.has_textures
          and not {"spp", "gradient_spp"} & spec.render.model_fields_set
          and indirect_only(problem, direct)):
        recipe.spp = recipe.gradient_spp = INDIRECT_SPP
        recipe.first_size = recipe.views * INDIRECT_SPP
        recipe.decide("spp", INDIRECT_SPP, f"no optimized scalar is seen directly: its gradient comes from paths of two "
                                           f"bounces or more, whose noise at 1 sample per pixel decides the steps' "
                                           f"direction; {INDIRECT_SPP} samples per pixel from the first iteration "
                                           f"(bench.first_spp)")
    elif spec.render.spp == 1 and spec.render.gradient_spp == 1:
        recipe.decide("spp", 1, "1 sample per pixel: the fastest to a given error in every scene measured; the "
                                "optimizer averages the noise across iterations")
    return recipe


def indirect_only(problem: Problem, direct: Callable[[], list[bool]] | None) -> bool:
    """True when no active scalar changes the light of the camera hits directly (the hidden
    object of the paper's Fig. 5): from the effect plan where the method made one, else from
    ``direct`` (:func:`services.solver.scene.facts.direct_reach`); False when neither says."""
    if problem.plan is not None:
        active = [s for s in problem.plan.scalars if s.active]
        return bool(active) and all(s.first_bounce is not None and s.first_bounce > 0 for s in active)
    if direct is None:
        return False
    reach = direct()
    seen = [reach[i] for i in problem.layout.scalars]
    return bool(seen) and not any(seen)


def _trust_growth(recipe: Recipe, measure: Callable[[], float | None] | None) -> None:
    closure = None if measure is None else measure()
    if closure is None:
        why = "the scene's closure was not measured" if measure is None else "no reflecting surface to measure it on"
        recipe.decide("trust_growth", CLOSED_GROWTH, f"{why}: the cautious growth of the trust region (3/2)")
        recipe.decide("trust_start", CLOSED_START, f"{why}: the cautious first step, one learning rate (Adam's)")
        return
    share = f"{closure:.0%} of the light a surface reflects hits another surface"
    if closure < CLOSED:
        recipe.trust_growth, recipe.trust_start = OPEN_GROWTH, OPEN_START
        recipe.decide("trust_growth", OPEN_GROWTH, f"{share}: the images are close to linear in the scalars, and "
                                                   f"the trust region doubles on steps that agree")
        recipe.decide("trust_start", OPEN_START, f"the same linearity: the first step may be {OPEN_START:g} learning "
                                                 f"rates long")
    else:
        recipe.trust_growth, recipe.trust_start = CLOSED_GROWTH, CLOSED_START
        recipe.decide("trust_growth", CLOSED_GROWTH, f"{share} (a closed scene): the images curve strongly in the "
                                                     f"albedos, and the trust region grows by 3/2 on steps that agree")
        recipe.decide("trust_start", CLOSED_START, "the same curvature: the first step is one learning rate long "
                                                   "(Adam's)")


def texture_batch(spec: JobSpec, recipe: Recipe, sensors: int) -> None:
    """A texture job's batch: every view, and :data:`TEXTURE_SPP` samples per pixel unless the
    job sets them. Each texel is seen by a few pixels only; at one view and 1 spp Adam's steps stay
    noise-dominated (``bench/results/textures-one-view.md``: 22.7 dB after 960 iterations, where
    every view at 16 spp reaches 34.8 dB in 60 iterations of the same total time,
    ``bench/results/textures.md``); every view at 1, 4, 32 or 64 spp, for the samples of 60
    iterations at 16, ends at 24.8, 29.1, 29.8 or 21.7 dB, short of the 30 dB that 16 spp reaches
    at iteration 20 (``bench/results/textures-spp.md``)."""
    recipe.views, recipe.adaptive_views = sensors, False
    recipe.decide("views", sensors, "a texture: every view per iteration (each texel is seen by few pixels; one view "
                                    "at a time leaves Adam's steps noise-dominated, bench/results/textures*.md)")
    if not {"spp", "gradient_spp"} & spec.render.model_fields_set:
        recipe.spp = recipe.gradient_spp = TEXTURE_SPP
        recipe.decide("spp", TEXTURE_SPP, f"a texture: {TEXTURE_SPP} samples per pixel (render.spp and gradient_spp "
                                          f"left unset)")
    recipe.first_size = recipe.views * recipe.gradient_spp


def grow_batch(recipe: Recipe, sensors: int, iteration: int) -> Decision | None:
    """Double the batch (the run's steps turned noise-dominated): the views per iteration while
    there are more, then the samples per pixel, up to :data:`MAX_GROWTH` times the first batch;
    None when it cannot grow."""
    if not recipe.adaptive_views or recipe.views * recipe.gradient_spp >= MAX_GROWTH * recipe.first_size:
        return None
    why = "the steps keep reversing (noise-dominated): "
    if recipe.views < sensors:
        recipe.views = min(2 * recipe.views, sensors)
        return recipe.decide("views", recipe.views, why + "twice the views per iteration", iteration)
    recipe.spp, recipe.gradient_spp = 2 * recipe.spp, 2 * recipe.gradient_spp
    return recipe.decide("spp", recipe.spp, why + "every view is in the batch: twice the samples per pixel",
                         iteration)

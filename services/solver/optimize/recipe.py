"""The recipe of a run: everything it will do, resolved once from the job
(:func:`services.solver.optimize.resolve.resolve`), frozen, written to ``plan.json`` as
``recipe``, and used to build the run (:mod:`.build`). Each choice the job left to the product
carries a :class:`Decision` with its reason.

The run changes nothing here. What it decides on the way (a larger batch when its steps turn
noise-dominated, the reason it stops) is a :class:`Decision` with the iteration it was taken at,
appended to ``plan.json``'s ``events``; the batch in use is the run's state (:class:`BatchNow`).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from services.solver.estimators.layout import DerivativeLayout
from services.solver.estimators.render import PathDepth
from services.solver.optimize.blur import BlurSchedule
from services.solver.optimize.stopping import StopRule
from services.solver.scene.effects import Effects


@dataclass(frozen=True)
class Decision:
    """A choice and its reason; ``iteration`` None: taken before the first iteration."""

    what: str           # "method", "optimizer", "views", "spp", "depth", "trust_growth", "stop", ...
    value: str | int | float
    reason: str
    iteration: int | None = None


@dataclass(frozen=True)
class Steps:
    """How the parameters move: the update rule and its settings (:mod:`.optimizers`)."""

    optimizer: str                   # "adam" | "levenberg-marquardt" | "gauss-newton"
    learning_rate: float
    final_learning_rate_ratio: float
    iterations: int
    betas: tuple[float, float]       # Adam's
    damping: float                   # Marquardt's lambda
    curvature: str                   # "successive" | "product" | "cross" (the job's ``hessian``)
    curvature_every: int             # the job's ``jacobian_every``
    trust_growth: float              # Levenberg-Marquardt's growth of the trust radius
    trust_start: float               # and its first radius, in learning rates
    restarts: tuple[int, ...] = ()   # iterations where a new stage starts (a remesh: :class:`Remesh`)

    def learning_rate_at(self, k: int) -> float:
        """Geometric decay over the stage of iteration ``k``: from ``learning_rate`` at its first
        iteration ``s`` to ``learning_rate · final_learning_rate_ratio`` at its last ``e``
        (``lr_k = lr · ratio^((k - s) / (e - s))``). One stage, ``[0, iterations - 1]``, unless
        ``restarts`` cut the run into several (each remeshed mesh starts its own optimization)."""
        start = max((r for r in self.restarts if r <= k), default=0)
        end = min((r for r in self.restarts if r > k), default=self.iterations) - 1
        if end <= start:
            return self.learning_rate
        return self.learning_rate * self.final_learning_rate_ratio ** ((k - start) / (end - start))

    @property
    def second_order(self) -> bool:
        return self.optimizer != "adam"


@dataclass(frozen=True)
class BatchRule:
    """The first batch (views per iteration, samples per pixel of the candidate and of the
    gradient) and whether the run may double it when its steps turn noise-dominated, up to
    ``max_growth`` times its first size (views x gradient samples)."""

    views: int
    spp: int
    gradient_spp: int
    grows: bool
    max_growth: int

    @property
    def first_size(self) -> int:
        return self.views * self.gradient_spp


@dataclass
class BatchNow:
    """The batch a run uses now (its state: a checkpoint keeps it)."""

    views: int
    spp: int
    gradient_spp: int

    @classmethod
    def first(cls, rule: BatchRule) -> BatchNow:
        return cls(rule.views, rule.spp, rule.gradient_spp)

    def grow(self, rule: BatchRule, sensors: int, iteration: int) -> Decision | None:
        """Double the batch (the steps turned noise-dominated): the views while there are more,
        then the samples per pixel, up to ``rule.max_growth`` times the first batch; None when it
        may not grow."""
        if not rule.grows or self.views * self.gradient_spp >= rule.max_growth * rule.first_size:
            return None
        why = "the steps keep reversing (noise-dominated): "
        if self.views < sensors:
            self.views = min(2 * self.views, sensors)
            return Decision("views", self.views, why + "twice the views per iteration", iteration)
        self.spp, self.gradient_spp = 2 * self.spp, 2 * self.gradient_spp
        return Decision("spp", self.spp, why + "every view is in the batch: twice the samples per pixel", iteration)


@dataclass(frozen=True)
class Remesh:
    """A shape job's remeshing schedule (the job's ``geometry.remesh_at``,
    :mod:`services.solver.optimize.remeshing`): before each iteration of ``at``, every optimized
    mesh is remeshed to edges of ``edge`` times its mean edge length in ``passes`` passes."""

    at: tuple[int, ...]
    edge: float
    passes: int

    def to_json(self) -> dict:
        return {"at": list(self.at), "edge": self.edge, "passes": self.passes}


@dataclass(frozen=True)
class Recipe:
    """Everything a run will do (module docstring).

    ``method``      the gradient method (what ``auto`` chose, or the job's)
    ``jacobian``    where the second-order steps' Jacobian comes from: ``method`` or
                    ``differential-field`` (``dL_theta`` at cached camera hits)
    ``fields_for``  the method the trained fields serve, whose effects were chosen (None: no field,
                    or the many-parameter head, which simulates every effect)
    ``effects``     what the fields simulate of the scene (:mod:`services.solver.scene.effects`)
    ``layout``      the derivatives carried: active scalars and their RGB channels
    ``radiance``, ``differential``  the fields the run trains (L_phi, dL_theta)
    """

    method: str
    jacobian: str
    fields_for: str | None
    depth: PathDepth
    effects: Effects | None
    layout: DerivativeLayout
    steps: Steps
    batch: BatchRule
    stop: StopRule
    decisions: tuple[Decision, ...]
    warnings: tuple[str, ...] = ()   # what the job's own choices cost (a truncated depth, a forced effect)
    texture_blocks: tuple[tuple[str, int], ...] = ()   # each texture's block side (1: its own resolution)
    radiance: bool = False       # whether the run trains L_phi
    differential: bool = False   # whether the run trains dL_theta
    #: per scalar, one unit of the optimizer's steps in the scalar's own units (empty: all 1;
    #: a rotation's, :meth:`services.solver.scene.params.ParameterSet.step_units`)
    step_units: tuple[float, ...] = ()
    #: spans ``(start, stop)`` of ``p`` whose Adam steps share one scale (a mesh's vertices:
    #: :class:`~services.solver.optimize.optimizers.adam.Adam`'s ``uniform``)
    uniform: tuple[tuple[int, int], ...] = ()
    #: a geometry job's coarse-to-fine blur of the loss (:mod:`.blur`; None: sharp images)
    blur: BlurSchedule | None = None
    #: a shape job's remeshing schedule (None: the triangles stay as loaded). ``layout``,
    #: ``step_units`` and ``uniform`` describe the scalars as loaded; after a remesh the run
    #: derives them again, by the same rules, for the new vertices (:mod:`.remeshing`)
    remesh: Remesh | None = None
    #: how the method meets the camera: ``candidate`` (``path``: traced; ``field``: ``L_phi`` at
    #: the first hits), ``first_hits`` (``fresh`` each iteration or ``cached`` once per job, at
    #: ``cache_spp`` samples per pixel) and ``head`` (the many-parameter head replaces the method)
    candidate: str = "path"
    first_hits: str = "fresh"
    cache_spp: int = 1
    head: bool = False
    #: every this many iterations, ``prb``'s unbiased ``dz/dp`` of the same views beside the
    #: method's, whose difference the answer corrects its bias by (0: never; :mod:`.answer`)
    bias_every: int = 0

    @staticmethod
    def is_hybrid(method: str, fields_for: str | None) -> bool:
        """Whether the trained fields serve another method than the gradient's ``method``: the
        Jacobian of the second-order steps is ``dL_theta`` (of ``ndrf-lhs``) at cached camera hits
        while ``method`` gives the candidate and ``dz/dp`` (the hybrid)."""
        return fields_for is not None and fields_for != method

    @property
    def hybrid(self) -> bool:
        """:meth:`is_hybrid` of this recipe's method and fields."""
        return self.is_hybrid(self.method, self.fields_for)

    def blur_at(self, k: int) -> float:
        """The loss's blur at iteration ``k``, in pixels (0: none)."""
        return 0.0 if self.blur is None else self.blur.at(k)

    def to_json(self) -> dict:
        return {"method": self.method, "optimizer": self.steps.optimizer, "jacobian": self.jacobian,
                "fields_for": self.fields_for, "views": self.batch.views, "spp": self.batch.spp,
                "gradient_spp": self.batch.gradient_spp, "grows": self.batch.grows,
                "max_growth": self.batch.max_growth, "depth": self.depth.describe(),
                "trust_growth": self.steps.trust_growth, "trust_start": self.steps.trust_start,
                "curvature": self.steps.curvature if self.steps.second_order else None,
                "stop": asdict(self.stop), "texture_blocks": dict(self.texture_blocks),
                "fields": {"radiance": self.radiance, "differential": self.differential},
                "step_units": list(self.step_units) or None, "uniform": [list(s) for s in self.uniform] or None,
                "blur": None if self.blur is None else self.blur.to_json(),
                "remesh": None if self.remesh is None else self.remesh.to_json(),
                "candidate": self.candidate, "first_hits": self.first_hits, "cache_spp": self.cache_spp,
                "head": self.head, "bias_every": self.bias_every,
                "decisions": [asdict(d) for d in self.decisions], "warnings": list(self.warnings)}

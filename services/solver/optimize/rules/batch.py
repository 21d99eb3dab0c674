"""The first batch of views per iteration and samples per pixel, and whether the run may grow it.

Rules, for ``views_per_iteration: "auto"``:

* **scalars**: one view per iteration at the first samples per pixel (:mod:`.first_spp`); under
  second-order steps the run doubles the batch when its steps keep reversing (noise-dominated),
  views while there are more, then samples per pixel, up to :data:`MAX_GROWTH` times its first
  size; kept as it is under Adam, whose moments average the noise. The fastest hand-written
  Mitsuba loop renders one view per iteration too (``python -m bench.mitsuba_loop``).
* **a texture** (:data:`TEXTURE`): every view at :data:`TEXTURE_SPP` spp per iteration; each
  texel is seen by few pixels, and at one view and 1 spp Adam's steps stay noise-dominated
  (``bench/results/textures*.md``).
* **geometry** (:data:`GEOMETRY`): every view at :data:`GEOMETRY_SPP` spp per iteration: the
  boundary term at 1 spp is noise (Mitsuba's pose tutorial renders 16), and a silhouette seen
  from one side leaves the pose's other directions free.

Samples per pixel the job sets (``render.spp``, ``render.gradient_spp``) are kept.
"""

from __future__ import annotations

from dataclasses import dataclass

from schemas.job import JobSpec
from services.solver.estimators.layout import DerivativeLayout
from services.solver.optimize.recipe import BatchRule
from services.solver.optimize.rules.first_spp import first_spp
from services.solver.optimize.rules.inputs import Decide, Measures, Parameters
from services.solver.scene.effects import Effects

#: A growing batch stops at this many times its first size (views x samples per pixel).
MAX_GROWTH = 16
#: Samples per pixel of a texture job whose job leaves them unset.
TEXTURE_SPP = 16
#: Samples per pixel of a geometry job whose job leaves them unset (Mitsuba's pose tutorial's).
GEOMETRY_SPP = 16


@dataclass(frozen=True)
class EveryView:
    """A job that renders every view per iteration: what it is, its samples per pixel where the
    job leaves them unset, and why (``plan.json``'s reasons)."""

    what: str
    spp: int
    views_why: str
    spp_why: str
    grows: bool        # whether the batch may grow under second-order steps


GEOMETRY = EveryView("geometry", GEOMETRY_SPP, "a silhouette seen from one side leaves the pose's other directions "
                     "free, and the boundary term is noisy", "the boundary term of a silhouette at 1 sample per pixel "
                     "is noise; ", grows=True)
TEXTURE = EveryView("a texture", TEXTURE_SPP, "each texel is seen by few pixels; one view at a time leaves Adam's "
                    "steps noise-dominated, bench/results/textures*.md", "", grows=False)


def batch(spec: JobSpec, method: str, optimizer: str, parameters: Parameters, effects: Effects | None,
          layout: DerivativeLayout, sensors: int, measures: Measures, decide: Decide) -> BatchRule:
    """The first batch of views and samples per pixel, and whether the run may grow it (module
    docstring)."""
    render, auto_views = spec.render, spec.views_per_iteration == "auto"
    unset = not {"spp", "gradient_spp"} & render.model_fields_set
    if auto_views and (parameters.has_geometry or parameters.has_textures):
        rule = GEOMETRY if parameters.has_geometry else TEXTURE
        decide("views", sensors, f"{rule.what}: every view per iteration ({rule.views_why})")
        spp, gradient_spp = render.spp, render.gradient_spp
        if unset:
            spp = gradient_spp = rule.spp
            decide("spp", rule.spp, f"{rule.what}: {rule.spp} samples per pixel ({rule.spp_why}render.spp and "
                                    f"gradient_spp left unset)")
        return BatchRule(sensors, spp, gradient_spp, grows=rule.grows and optimizer != "adam", max_growth=MAX_GROWTH)
    views = 1 if auto_views else min(int(spec.views_per_iteration), sensors)
    grows = auto_views and optimizer != "adam"
    if auto_views:
        start = (f"one of the {sensors} views per iteration (the fastest hand-written loop's batch too)"
                 if sensors > 1 else "the job's one view")
        decide("views", views, start + ("; the batch doubles whenever the steps turn noise-dominated: views first, "
                                        f"then samples per pixel (up to {MAX_GROWTH}x)" if grows
                                        else "; Adam's moments average the noise"))
    spp, gradient_spp = first_spp(spec, method, parameters, effects, layout, measures, decide, unset=unset)
    return BatchRule(views, spp, gradient_spp, grows=grows, max_growth=MAX_GROWTH)

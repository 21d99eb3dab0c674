"""Cost of one optimization iteration against path length, for ``prb`` and ``ndrf-rhs``.

In the closed hidden-object room (walls of albedo 0.5) light keeps bouncing: ``prb`` must trace
paths of ``max_depth`` vertices, and its cost grows with the depth it is given; below the depth
the light needs its gradient is biased. ``ndrf-rhs`` has no depth parameter: it traces one bounce and
the fields carry the rest, so there is one iteration of it to time (fine-tuning steps plus a
query), reported once with ``depth: None`` rather than copied per depth. The error of each is
against ``prb`` at depth 64 (converged), of the gradient images (``error``, dominated by
per-pixel noise at 16 spp) and of their sum over the pixels (``sum_error``: dz/dp for a loss that
weighs every pixel alike, where the noise averages out and a too-short depth shows as bias).
"""

from __future__ import annotations

import logging

from bench.common import problem, relative_error, timed
from services.solver.estimators.render import PathDepth

log = logging.getLogger(__name__)


def _errors(g, reference) -> dict:
    """Relative errors of the images (P, H, W, 3) and of their pixel sums (P, 3)."""
    return {"error": relative_error(g, reference),
            "sum_error": relative_error(g.sum(axis=(1, 2)), reference.sum(axis=(1, 2)))}


def run(quick: bool) -> dict:
    from schemas.solver import TrainingConfig
    from services.solver.estimators.methods import Fields, make_method
    from services.solver.estimators.methods.prb import Prb
    from services.solver.training.trainer import FieldTrainer

    depths = [2, 4, 8, 16] if quick else [2, 3, 4, 6, 8, 12, 16]
    spp, repeats = 16, (2 if quick else 3)
    prob = problem("hidden-object", ["hidden.reflectance.value"])
    reference = Prb(depth=PathDepth(64, None)).gradient_images(prob, Fields(), spp=256 if quick else 1024, seed=5)
    rows = []
    for depth in depths:
        method = Prb(depth=PathDepth(depth, None))
        method.gradient_images(prob, Fields(), spp=1, seed=0)           # compile outside the clock
        with timed() as t:
            for r in range(repeats):
                g = method.gradient_images(prob, Fields(), spp=spp, seed=r)
        rows.append({"method": "prb", "depth": depth, "seconds": t.seconds / repeats, **_errors(g, reference)})
    planned = problem("hidden-object", ["hidden.reflectance.value"], method="ndrf-rhs")
    config = TrainingConfig()
    trainer = FieldTrainer(planned, config, radiance=True, differential=True, seed=0)
    trainer.train(150 if quick else 600)
    ndrf = make_method("ndrf-rhs", planned.effects)
    fields = trainer.queried()
    ndrf.gradient_images(planned, fields, spp=1, seed=0)
    with timed() as t:
        for r in range(repeats):
            trainer.train(config.steps_per_iteration)
            g = ndrf.gradient_images(planned, fields, spp=spp, seed=r)
    per_iteration = t.seconds / repeats
    rows.append({"method": "ndrf-rhs", "depth": None, "seconds": per_iteration, **_errors(g, reference),
                 "note": f"{config.steps_per_iteration} training steps + a {spp}-spp query"})
    return {"spp": spp, "rows": rows}

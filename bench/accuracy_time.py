"""Gradient error against a high-spp ``prb`` reference as a function of wall time, per method.

``prb`` and ``direct`` spend time on samples (spp); ``radiance-cache``, ``ndrf-lhs`` and
``ndrf-rhs`` on training steps (the clock runs through training; each evaluation adds its query
time) and query spp. All in one process on one machine, so the ratios hold.
"""

from __future__ import annotations

import logging

from bench.common import problem, relative_error, timed
from services.solver.estimators.render import PathDepth

log = logging.getLogger(__name__)

SCENES = {  # scene: (parameter, what it shows)
    "cornell-box": ("red.reflectance.value", "diffuse interreflection"),
    "hidden-object": ("hidden.reflectance.value", "a parameter seen only through interreflection"),
    "glossy-box": ("metal.alpha.value", "a glossy roughness"),
}


def run(quick: bool) -> dict:
    from schemas.solver import TrainingConfig
    from services.solver.estimators.methods import Fields, make_method
    from services.solver.training.trainer import FieldTrainer

    reference_spp = 512 if quick else 4096
    sample_spp = [1, 4, 16, 64] if quick else [1, 4, 16, 64, 256, 1024]
    checkpoints = [50, 200] if quick else [50, 100, 200, 400, 800]
    query_spp = {"ndrf-lhs": [1, 16], "ndrf-rhs": [4, 16, 64], "radiance-cache": [4, 16, 64]}
    if quick:
        query_spp = {"ndrf-lhs": [4], "ndrf-rhs": [16], "radiance-cache": [16]}
    out = {}
    for scene, (key, what) in SCENES.items():
        log.info("accuracy vs time: %s", scene)
        prob = problem(scene, [key])
        with timed() as t_ref:
            reference = make_method("prb", None, PathDepth(12, None)).gradient_images(
                prob, Fields(), spp=reference_spp, seed=999)
        points = []
        for name in ("prb", "direct"):
            method = make_method(name)
            method.gradient_images(prob, Fields(), spp=1, seed=0)          # compile once, outside the clock
            for spp in sample_spp:
                with timed() as t:
                    g = method.gradient_images(prob, Fields(), spp=spp, seed=spp)
                points.append({"method": name, "spp": spp, "steps": 0, "seconds": t.seconds,
                               "error": relative_error(g, reference)})
        planned = problem(scene, [key], method="ndrf-rhs")
        trainer = FieldTrainer(planned, TrainingConfig(), radiance=True, differential=True, seed=0)
        # one trainer for both fields; a radiance cache is charged only the seconds of L_phi's steps
        spent = {"radiance": 0.0, "both": 0.0}
        done = 0
        for steps in checkpoints:
            for stats in trainer.train(steps - done):
                spent["radiance"] += stats.radiance_seconds
                spent["both"] += stats.seconds
            done = steps
            fields = trainer.queried()
            for name, spps in query_spp.items():
                method = make_method(name, planned.effects)
                training = spent["radiance"] if name == "radiance-cache" else spent["both"]
                for spp in spps:
                    with timed() as t:
                        g = method.gradient_images(planned, fields, spp=spp, seed=spp)
                    points.append({"method": name, "spp": spp, "steps": steps, "seconds": training + t.seconds,
                                   "training_seconds": training, "error": relative_error(g, reference)})
        out[scene] = {"key": key, "shows": what, "reference_spp": reference_spp,
                      "reference_seconds": t_ref.seconds, "points": points}
    return out

"""What the chosen effects save: the same gradient computed with the plan, and with everything the
plan skipped forced back on (``effects`` overrides). Time per training step (or per gradient for
methods without fields) for each case, in one run."""

from __future__ import annotations

import logging

from bench.common import timed

log = logging.getLogger(__name__)

CASES = [  # name, scene, keys, method, overrides that undo the plan's savings
    ("Cornell box, red wall: RGB channels merged", "cornell-box", ["red.reflectance.value"], "ndrf-lhs",
     {"merge_channels": False}),
    ("Cornell box, light intensity: no L_phi, no (∂f) L", "cornell-box", ["light.emitter.radiance.value"], "ndrf-lhs",
     {"radiance_field": "on", "bsdf_term": "on"}),
    ("Closet box: a parameter no camera path reaches is dropped", "closet-box", ["red.reflectance.value",
                                                                             "hidden-paint.reflectance.value"],
     "ndrf-rhs", {"drop_unreachable": False}),
    ("Mirror box: delta depth 1 instead of 8", "mirror-box", ["sphere.reflectance.value"], "direct",
     {"delta_depth": 8}),
]


def _problem(scene: str, keys: list[str], method: str, overrides: dict):
    from schemas.job import EffectOverrides
    from services.solver.estimators.methods import method_class
    from services.solver.estimators.problem import Problem
    from services.solver.scene.effects import choose_effects
    from services.solver.scene.facts import probe_scene
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    loaded = load_scene(builtin=scene, resolution=(64, 64))
    prob = Problem(loaded, ParameterSet(loaded.params, keys))
    prob.simulate(choose_effects(probe_scene(loaded, prob.parameters), method, method_class(method).uses,
                                EffectOverrides(**overrides)))
    return prob


def run(quick: bool) -> dict:
    from schemas.solver import TrainingConfig
    from services.solver.estimators.methods import make_method
    from services.solver.training.trainer import fields_of, trainer_for

    steps = 15 if quick else 40
    rows = []
    for name, scene, keys, method, undo in CASES:
        timings = {}
        for label, overrides in (("planned", {}), ("everything on", undo)):
            prob = _problem(scene, keys, method, overrides)
            estimator = make_method(method, prob.effects)
            trainer = trainer_for(prob, estimator, TrainingConfig(), seed=0)
            if trainer is not None:
                trainer.train(3)
                with timed() as t:
                    trainer.train(steps)
                timings[label] = t.seconds / steps
            else:
                estimator.gradient_images(prob, fields_of(None), spp=16, seed=99)      # compile at the timed size
                with timed() as t:
                    for r in range(5):
                        estimator.gradient_images(prob, fields_of(None), spp=16, seed=r)
                timings[label] = t.seconds / 5
        rows.append({"case": name, "unit": "s / training step" if trainer is not None else "s / gradient (16 spp)",
                     "planned": timings["planned"], "everything on": timings["everything on"],
                     "saving": 1 - timings["planned"] / timings["everything on"]})
        log.info("%s: %.3f vs %.3f", name, timings["planned"], timings["everything on"])
    return {"rows": rows}

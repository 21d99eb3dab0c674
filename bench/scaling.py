"""Training-step time and peak memory against the number of optimized scalars (1..64).

The parameter is a single-channel bitmap texture on the back wall of the Cornell box with
4, 9, 16, 36 or 64 texels; the output layer of ``dL_theta`` grows with the scalars (3 outputs per
texel: a grey texel changes all three channels). Each size runs in its own process so that the
peak resident memory is that of the size alone.
"""

from __future__ import annotations

import json
import logging
import resource
import subprocess
import sys
import time

log = logging.getLogger(__name__)


def textured_box(side: int) -> dict:
    import numpy as np

    from services.solver.backend import use_mitsuba
    from services.solver.scene.builtin import cornell_box

    mi = use_mitsuba()
    d = cornell_box()
    texels = np.full((side, side, 1), 0.7, dtype=np.float32)
    d["poster"] = {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(texels),
                                                      "raw": True, "filter_type": "nearest"}}
    d["back"]["bsdf"] = {"type": "ref", "id": "poster"}
    return d


def measure(side: int, steps: int) -> dict:
    """Runs in a child process: plan, build the trainer, time ``steps`` training steps."""
    from services.solver.backend import use_mitsuba, use_torch

    use_mitsuba(), use_torch()
    from schemas.solver import TrainingConfig
    from services.solver.estimators.methods import method_class
    from services.solver.estimators.problem import Problem
    from services.solver.scene.effects import choose_effects
    from services.solver.scene.facts import probe_scene
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.training.trainer import FieldTrainer

    scene = load_scene(mitsuba_dict=textured_box(side), resolution=(64, 64))
    prob = Problem(scene, ParameterSet(scene.params, ["back.bsdf.reflectance.data"]))
    prob.simulate(choose_effects(probe_scene(scene, prob.parameters), "ndrf-rhs", method_class("ndrf-rhs").uses))
    trainer = FieldTrainer(prob, TrainingConfig(), radiance=True, differential=True, seed=0)
    trainer.train(5)                                          # compile and warm up outside the clock
    start = time.perf_counter()
    stats = trainer.train(steps)
    elapsed = time.perf_counter() - start
    return {"scalars": prob.parameters.n, "outputs": prob.layout.outputs,
            "step_seconds": elapsed / steps, "differential_seconds": sum(s.differential_seconds for s in stats) / steps,
            "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def run(quick: bool) -> dict:
    rows = []
    for side in (2, 4, 8) if quick else (2, 3, 4, 6, 8):     # 4 to 64 scalars (Mitsuba widens a 1x1 bitmap)
        log.info("scaling: %d scalars", side * side)
        code = f"import json, bench.scaling as s; print(json.dumps(s.measure({side}, {15 if quick else 40})))"
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
    return {"rows": rows}

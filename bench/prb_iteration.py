"""Seconds per ``prb`` iteration before and after the adjoint path, for 3 and 24 scalars.

*Before* (the loop until this change): a path-traced candidate, then per-scalar gradient images by
forward mode (one ``prb`` render per scalar), contracted with dz/dy. *After*: one differentiable
render gives the candidate, and one adjoint pass gives dz/dp for every scalar
(``Prb.candidate_and_gradient``). Both are timed in this process, alternating, on the same scene
and settings (64x64, 16 spp, depth 12), after a warm-up that compiles every kernel.

    python -m bench.prb_iteration [--repeats 5]
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)


def _problem(scalars: int):
    from bench.scaling import textured_box
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    if scalars == 3:
        scene = load_scene(builtin="cornell-box", resolution=(64, 64))
        return Problem(scene, ParameterSet(scene.params, ["red.reflectance.value"]))
    side = {24: (4, 6)}[scalars]
    d = textured_box(1)
    import mitsuba as mi

    d["poster"]["reflectance"]["bitmap"] = mi.Bitmap(np.full((side[0], side[1], 1), 0.7, np.float32))
    scene = load_scene(mitsuba_dict=d, resolution=(64, 64))
    return Problem(scene, ParameterSet(scene.params, ["back.bsdf.reflectance.data"]))


def before(problem, method, loss, spp: int, seed: int) -> np.ndarray:
    """The old loop: candidate, per-scalar forward-mode images, contraction."""
    from services.solver.estimators.methods import Fields, contract
    from services.solver.estimators.render import render

    candidate = render(problem, spp=spp, seed=seed, max_depth=12)
    _, dz_dy = loss(candidate)
    return contract(method.images(problem, Fields(), spp=spp, seed=seed + 1), dz_dy)


def after(problem, method, loss, spp: int, seed: int) -> np.ndarray:
    return method.candidate_and_gradient(problem, None, loss, spp=spp, gradient_spp=spp, seed=seed, max_depth=12)[2]


def run(repeats: int, spp: int = 16) -> dict:
    from services.solver.backend import use_mitsuba, use_torch

    use_mitsuba(), use_torch()
    from services.solver.estimators.methods import make_method
    from services.solver.estimators.render import render
    from services.solver.optimize.losses import image_loss

    out = {}
    for scalars in (3, 24):
        problem = _problem(scalars)
        assert problem.parameters.n == scalars, problem.parameters.n
        target = render(problem, spp=64, seed=1, max_depth=12) * 1.2
        loss = lambda y, target=target: image_loss("l2", y, target)
        method = make_method("prb", max_depth=12)
        before(problem, method, loss, spp, 0), after(problem, method, loss, spp, 0)   # compile outside the clock
        times = {"before": [], "after": []}
        for r in range(repeats):
            for name, step in (("before", before), ("after", after)):
                start = time.perf_counter()
                step(problem, method, loss, spp, 10 + r)
                times[name].append(time.perf_counter() - start)
        out[scalars] = {k: float(np.median(v)) for k, v in times.items()}
        out[scalars]["speedup"] = out[scalars]["before"] / out[scalars]["after"]
        log.info("prb iteration, %d scalars: %s", scalars, out[scalars])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--out", type=Path, default=Path("bench/results/prb_iteration.json"))
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    result = run(args.repeats)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2) + "\n")
    for scalars, row in result.items():
        print(f"{scalars:3d} scalars: before {row['before']:.2f} s, after {row['after']:.2f} s "
              f"({row['speedup']:.1f}x)")


if __name__ == "__main__":
    main()

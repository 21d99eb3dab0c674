"""Seconds per training step with and without the residual-batch pool (``training.pool``).

``python -m bench.investigations.pool_step [--steps N]``: the Cornell box at 64x64, the red wall's albedo,
``ndrf-lhs``'s fields, the default training configuration; each setting in its own process, 5
steps outside the clock (kernel compilation), then ``N`` timed steps. Writes
``bench/results/pool_step.json``.
"""

from __future__ import annotations

import argparse
import json
import logging
import subprocess
import sys
import time
from pathlib import Path

log = logging.getLogger(__name__)
OUT = Path(__file__).resolve().parents[1] / "results" / "pool_step.json"


def measure(pool: bool, steps: int) -> dict:
    """Runs in a child process: time ``steps`` training steps with the pool on or off."""
    from schemas.solver import TrainingConfig
    from services.solver.backend import use_mitsuba, use_torch

    use_mitsuba(), use_torch()
    from services.solver.estimators.methods import method_class
    from services.solver.estimators.problem import Problem
    from services.solver.scene.effects import choose_effects
    from services.solver.scene.facts import probe_scene
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.training.trainer import FieldTrainer

    scene = load_scene(builtin="cornell-box", resolution=(64, 64))
    problem = Problem(scene, ParameterSet(scene.params, ["red.reflectance.value"]))
    problem.simulate(choose_effects(probe_scene(scene, problem.parameters), "ndrf-lhs", method_class("ndrf-lhs").uses))
    config = TrainingConfig.model_validate({"pool": {"enabled": pool}})
    trainer = FieldTrainer(problem, config, radiance=True, differential=True, seed=0)
    trainer.train(5)
    start = time.perf_counter()
    trainer.train(steps)
    return {"pool": pool, "steps": steps, "step_seconds": (time.perf_counter() - start) / steps}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.pool_step", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=60)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    rows = []
    for pool in (False, True):
        code = f"import json, bench.investigations.pool_step as b; print(json.dumps(b.measure({pool}, {args.steps})))"
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
        rows.append(json.loads(result.stdout.strip().splitlines()[-1]))
        log.info("pool %s: %.3f s per step", pool, rows[-1]["step_seconds"])
    OUT.write_text(json.dumps({"rows": rows, "ratio_without_over_with": rows[0]["step_seconds"] / rows[1]["step_seconds"]},
                              indent=1) + "\n")
    log.info("without / with the pool: %.2fx", rows[0]["step_seconds"] / rows[1]["step_seconds"])


if __name__ == "__main__":
    main()

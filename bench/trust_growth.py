"""Levenberg-Marquardt's trust-region growth in an open and a closed scene.

``python -m bench.trust_growth [--jobs room-open-8,room-closed-8] [--seeds 0,1,2] [--growths 1.5,2]``

The default job of each ``examples/`` file (:func:`bench.regime.default_job`), once per seed and
per growth of the trust radius on agreeing steps, with the growth forced for every scene (the
recipe otherwise takes it from the scene's closure: ``services.solver.optimize.recipe``). Reported:
the iteration and the seconds (on :func:`bench.regime.run_product`'s clock) at which the largest
parameter error first falls below ``--target-error``. The recipe's rule rests on this table.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from bench.common import machine, markdown_table, write_markdown
from bench.regime import default_job, merge, run_product

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent


def run(name: str, seeds: list[int], growths: list[float], target_error: float, budget: float) -> dict[float, list]:
    """``{growth: [(iteration, seconds) or None per seed]}`` for the job ``examples/<name>.json``."""
    from services.solver.optimize import recipe

    base = default_job(json.loads((ROOT / "examples" / f"{name}.json").read_text()))
    run_product(merge(base, {"targets": {"synthetic": {"spp": 1}}}), target_error, iterations=2)  # kernels, untimed
    saved = recipe.OPEN_GROWTH, recipe.CLOSED_GROWTH
    out: dict[float, list] = {}
    try:
        for growth in growths:
            recipe.OPEN_GROWTH = recipe.CLOSED_GROWTH = growth
            out[growth] = []
            for seed in seeds:
                reached = run_product(dict(base, seed=seed), target_error, budget=budget)["reached"]
                out[growth].append(None if reached is None else (reached["iteration"], reached["seconds"]))
                log.info("%s growth %s seed %d: %s", name, growth, seed, out[growth][-1])
    finally:
        recipe.OPEN_GROWTH, recipe.CLOSED_GROWTH = saved
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.trust_growth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", default="room-open-8,room-closed-8")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--growths", default="1.5,2")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--budget", type=float, default=8.0, help="stop each run after this many seconds")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "trust_growth.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    seeds = [int(v) for v in args.seeds.split(",")]
    growths = [float(v) for v in args.growths.split(",")]
    results = {name: run(name, seeds, growths, args.target_error, args.budget)
               for name in [j.strip() for j in args.jobs.split(",") if j.strip()]}
    args.out.write_text(json.dumps({"machine": machine(), "seeds": seeds, "target_error": args.target_error,
                                    "results": {n: {str(g): r for g, r in rows.items()} for n, rows in results.items()}},
                                   indent=1))
    lines = [[name, f"{growth:g}", ", ".join("not reached" if r is None else f"it. {r[0]} ({r[1]:.2f} s)" for r in runs)]
             for name, rows in results.items() for growth, runs in rows.items()]
    text = markdown_table(["job", "trust growth", f"first max error < {args.target_error}, seeds {args.seeds}"], lines)
    write_markdown(args.out, "bench.trust_growth", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

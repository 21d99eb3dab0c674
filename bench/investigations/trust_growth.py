"""Levenberg-Marquardt's trust region in an open and a closed scene: its growth and its start.

``python -m bench.investigations.trust_growth [--jobs room-open-8,room-closed-8] [--seeds 0,1,2] [--growths 1.5,2]
[--starts 1,4]``

The default job of each ``examples/`` file (:func:`bench.regime.default_job`), once per seed, per
growth of the trust radius on agreeing steps and per first radius (in learning rates), with both
forced for every scene (the recipe otherwise takes them from the scene's closure:
``services.solver.optimize.recipe``). Reported:
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

ROOT = Path(__file__).resolve().parents[2]


def run(name: str, seeds: list[int], growths: list[float], starts: list[float], target_error: float,
        budget: float) -> dict[tuple[float, float], list]:
    """``{(growth, start): [(iteration, seconds) or None per seed]}`` for ``examples/<name>.json``."""
    from services.solver.optimize import recipe

    base = default_job(json.loads((ROOT / "examples" / f"{name}.json").read_text()))
    run_product(merge(base, {"targets": {"synthetic": {"spp": 1}}}), target_error, iterations=2)  # kernels, untimed
    saved = recipe.OPEN_GROWTH, recipe.CLOSED_GROWTH, recipe.OPEN_START, recipe.CLOSED_START
    out: dict[tuple[float, float], list] = {}
    try:
        for growth in growths:
            for start in starts:
                recipe.OPEN_GROWTH = recipe.CLOSED_GROWTH = growth
                recipe.OPEN_START = recipe.CLOSED_START = start
                runs = out[(growth, start)] = []
                for seed in seeds:
                    reached = run_product(dict(base, seed=seed), target_error, budget=budget)["reached"]
                    runs.append(None if reached is None else (reached["iteration"], reached["seconds"]))
                    log.info("%s growth %s start %s seed %d: %s", name, growth, start, seed, runs[-1])
    finally:
        recipe.OPEN_GROWTH, recipe.CLOSED_GROWTH, recipe.OPEN_START, recipe.CLOSED_START = saved
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.trust_growth", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", default="room-open-8,room-closed-8")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--growths", default="1.5,2")
    parser.add_argument("--starts", default="1,4", help="first trust radii, in learning rates")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--budget", type=float, default=8.0, help="stop each run after this many seconds")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "trust_growth.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    seeds = [int(v) for v in args.seeds.split(",")]
    growths = [float(v) for v in args.growths.split(",")]
    starts = [float(v) for v in args.starts.split(",")]
    results = {name: run(name, seeds, growths, starts, args.target_error, args.budget)
               for name in [j.strip() for j in args.jobs.split(",") if j.strip()]}
    args.out.write_text(json.dumps({"machine": machine(), "seeds": seeds, "target_error": args.target_error,
                                    "results": {n: {f"growth {g:g} start {s:g}": r for (g, s), r in rows.items()}
                                                for n, rows in results.items()}},
                                   indent=1))
    lines = [[name, f"{growth:g}", f"{start:g}",
              ", ".join("not reached" if r is None else f"it. {r[0]} ({r[1]:.2f} s)" for r in runs)]
             for name, rows in results.items() for (growth, start), runs in rows.items()]
    text = markdown_table(["job", "trust growth", "first radius (learning rates)",
                           f"first max error < {args.target_error}, seeds {args.seeds}"], lines)
    write_markdown(args.out, "bench.investigations.trust_growth", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

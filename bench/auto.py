"""Is the default job (``auto``) at least as fast as the best hand-written Mitsuba loop?

``python -m bench.auto [--jobs demo,hidden-object,room-open-8,room-closed-8] [--budget 60] [--seeds 0,1,2]
[--loop-spp 1,4] [--loop-rr 5,off] [--loop-views 1,2,4,all]``

For each job of ``examples/`` (reduced to its scene, parameters, targets and iterations: what a
user gets without tuning anything), in one process: :mod:`bench.regime`'s race of the loop's grid
(``spp`` {1, 4}, Russian roulette {5, off}, views per iteration {1, 2, 4, all}) against the
default job. Reported per job: the best loop and its seconds to ``--target-error``, the default
job's (decision time included), their ratio, and the recipe ``auto`` chose with the decisions it
took on the way. With several ``--seeds`` the default job runs once per seed (its row ``default``
is the first seed's) and the table gives the median and the slowest seed too: one run's time to
0.02 depends on the noise of its first steps.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown
from bench.mitsuba_loop import best
from bench.regime import race

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
JOBS = ("demo", "hidden-object", "room-open-8", "room-closed-8")


def summary(results: dict[str, dict]) -> str:
    lines = []
    for name, rows in results.items():
        found = best({k: v for k, v in rows.items() if k.startswith("loop")})
        default = rows["default"]
        runs = [r for k, r in rows.items() if k == "default" or k.startswith("default seed")]
        times = [r["reached"]["seconds"] if r["reached"] else float("inf") for r in runs]
        mine = float(np.median(times)) if np.isfinite(np.median(times)) else None
        theirs = found[1]["reached"]["seconds"] if found else None
        ratio = f"{mine / theirs:.2f}x" if mine is not None and theirs else (
            "reached where no loop did" if mine is not None else "-")
        if len(runs) > 1 and mine is not None:
            worst = max(times)
            ratio += (f" (slowest of {len(runs)} seeds: " + (f"{worst / theirs:.2f}x)" if theirs and np.isfinite(worst)
                                                              else f"{worst:.2f} s)"))
        recipe = default["recipe"]
        later = [f"{d['what']} {d['value']} at it. {d['iteration']}" for d in recipe["decisions"]
                 if d["iteration"] is not None]
        lines.append([name, f"{found[0][5:]}: {theirs:.2f} s" if found else "not reached",
                      (f"{mine:.2f} s" + (" (median)" if len(runs) > 1 else "")) if mine is not None
                      else "not reached", ratio,
                      f"{recipe['method']}, {recipe['optimizer']}" + (f"; {', '.join(later[:4])}" if later else "")])
    return markdown_table(["job", "best loop: seconds to 0.02", "default job", "default / best loop", "auto's recipe"],
                          lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.auto", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", default=",".join(JOBS))
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--budget", type=float, default=60.0, help="stop each row after this many seconds")
    parser.add_argument("--seeds", default="0", help="seeds of the default job (the median is reported)")
    parser.add_argument("--loop-spp", default="1,4")
    parser.add_argument("--loop-rr", default="5,off")
    parser.add_argument("--loop-views", default="1,2,4,all")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "auto.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    results = {}
    for name in [j.strip() for j in args.jobs.split(",") if j.strip()]:
        job = json.loads((ROOT / "examples" / f"{name}.json").read_text())
        seeds = [int(v) for v in args.seeds.split(",") if v.strip()]
        rows = {"default" if i == 0 else f"default seed {seed}": {"seed": seed} for i, seed in enumerate(seeds)}
        results[name] = race(job, rows, target_error=args.target_error, budget=args.budget,
                             loop_spp=[int(v) for v in args.loop_spp.split(",")],
                             loop_rr=[None if v.strip() == "off" else int(v) for v in args.loop_rr.split(",")],
                             loop_views=[None if v.strip() == "all" else int(v) for v in args.loop_views.split(",")])
        args.out.write_text(json.dumps({"machine": machine(), "target_error": args.target_error,
                                        "results": results}, indent=1))
    text = summary(results)
    write_markdown(args.out, "bench.auto", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

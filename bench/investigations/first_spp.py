"""Samples per pixel of ``prb``'s first batch, in a scene whose scalar is seen directly and in one
whose scalar is not.

``python -m bench.investigations.first_spp [--jobs hidden-object,demo] [--seeds 0,1,2] [--spps 1,4,8,16]``

The default job of each ``examples/`` file (:func:`bench.regime.default_job`: ``auto`` chooses
everything else), once per seed and per first samples per pixel, set through the job's
``render.spp`` and ``render.gradient_spp`` (the batch still grows when the steps turn
noise-dominated). Reported: the iteration and the seconds (on :func:`bench.regime.run_product`'s
clock) at which the largest parameter error first falls below ``--target-error`` within the job's
own iterations, and the median seconds per iteration. ``auto``'s rule for scalars seen only
through interreflection (``services.solver.optimize.rules.first_spp.indirect_only``) rests on this table.
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


def run(name: str, seeds: list[int], spps: list[int], target_error: float, budget: float) -> dict[int, list]:
    """``{spp: [{"reached": (iteration, seconds) or None, "final": error, "per_iteration": s}, ...] per seed}``."""
    base = default_job(json.loads((ROOT / "examples" / f"{name}.json").read_text()))
    run_product(merge(base, {"targets": {"synthetic": {"spp": 1}}}), target_error, iterations=2)  # kernels, untimed
    out: dict[int, list] = {}
    for spp in spps:
        out[spp] = []
        for seed in seeds:
            row = run_product(merge(base, {"seed": seed, "render": {"spp": spp, "gradient_spp": spp}}),
                              target_error, budget=budget)
            reached = row["reached"]
            out[spp].append({"reached": None if reached is None else (reached["iteration"], reached["seconds"]),
                             "final": row["final_error"], "per_iteration": row["seconds_per_iteration"]})
            log.info("%s spp %d seed %d: %s", name, spp, seed, out[spp][-1])
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.first_spp", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", default="hidden-object,demo")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--spps", default="1,4,8,16")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--budget", type=float, default=20.0, help="stop each run after this many seconds")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "first_spp.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    seeds = [int(v) for v in args.seeds.split(",")]
    spps = [int(v) for v in args.spps.split(",")]
    results = {name: run(name, seeds, spps, args.target_error, args.budget)
               for name in [j.strip() for j in args.jobs.split(",") if j.strip()]}
    args.out.write_text(json.dumps({"machine": machine(), "seeds": seeds, "target_error": args.target_error,
                                    "results": {n: {str(s): r for s, r in rows.items()} for n, rows in results.items()}},
                                   indent=1))
    lines = []
    for name, rows in results.items():
        for spp, runs in rows.items():
            first = ", ".join(f"not reached (final {r['final']:.3f})" if r["reached"] is None
                              else f"it. {r['reached'][0]} ({r['reached'][1]:.2f} s)" for r in runs)
            per = sorted(r["per_iteration"] for r in runs if r["per_iteration"] is not None)
            lines.append([name, spp, first, f"{per[len(per) // 2]:.3f}" if per else "-"])
    text = markdown_table(["job", "first spp", f"first max error < {args.target_error}, seeds {args.seeds}",
                           "s / iteration (median seed)"], lines)
    write_markdown(args.out, "bench.investigations.first_spp", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

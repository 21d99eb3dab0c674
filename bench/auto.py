"""Does ``"method": "auto"`` pick the method that is fastest when each one is run? (issue 11)

``python -m bench.auto [--cells demo,hidden-object,...] [--trial-only] [--out bench/results/auto.json]``

For each cell (a job file and changes to it), in one process: the trial of an ``auto`` job
(:func:`services.solver.optimize.auto.choose_method`, exactly what the loop runs) predicts every
candidate's seconds for the job's iterations; then each candidate runs the whole job through the
product's loop (``bench.regime.run_variant``). Reported per cell and method: predicted and
measured seconds (iteration records summed: warm-up and iterations, without the scene loading and
target rendering every method shares), the time at which the largest parameter error first falls
below ``--target-error``, and the final error. The measured-fastest method is the first to reach
the target error; if none does, the one with the smallest total (the same budget). A cell counts
against ``auto`` when its pick is not the measured-fastest and the two differ by more than 1.5x
(the issue's criterion).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

from bench.common import chosen, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent

#: name -> (job file, changes)
CELLS: dict[str, tuple[str, dict]] = {
    "demo": ("examples/demo.json", {}),
    "hidden-object": ("examples/hidden-object.json", {}),
    "bright-room-adam": ("examples/bright-room.json", {}),
    "bright-room-gauss-newton": ("examples/bright-room.json", {"optimizer": "gauss-newton"}),
    "room-open-8": ("examples/room-open-8.json", {}),
    "room-closed-8-gauss-newton": ("examples/room-closed-8.json", {"optimizer": "gauss-newton"}),
}

#: run without --cells (the rooms' whole runs take about an hour)
DEFAULT_CELLS = ("demo", "hidden-object", "bright-room-adam", "bright-room-gauss-newton")


def measured_fastest(runs: dict[str, dict]) -> tuple[str, float]:
    """The measured-fastest method and its seconds (see the module docstring)."""
    reached = {m: r["reached"]["seconds"] for m, r in runs.items() if r["reached"]}
    if reached:
        best = min(reached, key=reached.__getitem__)
        return best, reached[best]
    best = min(runs, key=lambda m: runs[m]["measured_seconds"])
    return best, runs[best]["measured_seconds"]


def verdict(cell: dict) -> str:
    """"right", "close" (wrong pick, within 1.5x of the fastest) or "wrong"."""
    runs, picked = cell["runs"], cell["picked"]
    best, seconds = measured_fastest(runs)
    if picked == best:
        return "right"
    mine = runs[picked]["reached"]["seconds"] if runs[picked]["reached"] else None
    if mine is None and any(r["reached"] for r in runs.values()):
        return "wrong"
    mine = mine if mine is not None else runs[picked]["measured_seconds"]
    return "close" if mine <= 1.5 * seconds else "wrong"


def run_cell(job: dict, target_error: float, trial_only: bool = False) -> dict:
    from bench.regime import run_variant
    from schemas.job import JobSpec
    from schemas.methods import AUTO_CANDIDATES
    from services.solver.optimize.auto import choose_method
    from services.solver.optimize.setup import prepare

    choice = choose_method(prepare(JobSpec.model_validate(dict(job, method="auto"))))
    predicted = {p.method: p.total_seconds for p in choice.predictions}
    runs = {}
    for method in () if trial_only else AUTO_CANDIDATES:
        log.info("auto bench: running %s", method)
        r = run_variant(dict(job, method=str(method)), target_error)
        runs[str(method)] = {"predicted_seconds": predicted[str(method)], "measured_seconds": r["curve"][-1]["seconds"],
                             "first_iteration_seconds": r["first_iteration_seconds"],
                             "seconds_per_iteration": r["seconds_per_iteration"], "reached": r["reached"],
                             "final_error": r["final_error"], "status": r["status"]}
    return {"picked": choice.method, "reason": choice.reason, "trial_seconds": choice.trial_seconds,
            "trial": choice.to_json(), "runs": runs, "predicted": predicted}


def trial_table(cells: dict) -> str:
    """``--trial-only``: the pick and every prediction (compare with ``bench.regime``'s whole runs)."""
    rows = [[name, cell["picked"], "; ".join(f"{m} {s:.0f} s" for m, s in sorted(cell["predicted"].items(),
                                                                                   key=lambda kv: kv[1])),
             f"{cell['trial_seconds']:.1f}"] for name, cell in cells.items()]
    return markdown_table(["cell", "auto picked", "predicted seconds for the job", "trial s"], rows)


def table(cells: dict, target_error: float) -> str:
    rows = []
    for name, cell in cells.items():
        best, _ = measured_fastest(cell["runs"])
        for method, r in cell["runs"].items():
            reached = r["reached"]
            rows.append([name, method + (" **(auto)**" if method == cell["picked"] else ""),
                         f"{r['predicted_seconds']:.1f}", f"{r['measured_seconds']:.1f}",
                         f"{r['measured_seconds'] / r['predicted_seconds']:.2f}",
                         f"{reached['iteration']} ({reached['seconds']:.1f} s)" if reached else "not reached",
                         f"{r['final_error']:.3f}", "fastest" if method == best else ""])
        rows.append([name, f"verdict: {verdict(cell)}; trial {cell['trial_seconds']:.1f} s", "", "", "", "", "", ""])
    return markdown_table(["cell", "method", "predicted s", "measured s", "measured / predicted",
                           f"error < {target_error} at", "final max error", ""], rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.auto", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cells", default=",".join(DEFAULT_CELLS),
                        help=f"subset of {', '.join(CELLS)} (default: {', '.join(DEFAULT_CELLS)})")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "auto.json")
    parser.add_argument("--trial-only", action="store_true",
                        help="run only each cell's trial (the pick and its predictions), not the whole jobs")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    from bench.regime import _merge

    cells = {}
    for name in chosen(args.cells, CELLS, parser, "cell"):
        path, change = CELLS[name]
        log.info("auto bench: cell %s", name)
        cells[name] = run_cell(_merge(json.loads((ROOT / path).read_text()), change), args.target_error,
                               args.trial_only)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"target_error": args.target_error, "cells": cells}, indent=1))
    text = trial_table(cells) if args.trial_only else table(cells, args.target_error)
    write_markdown(args.out, "bench.auto", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

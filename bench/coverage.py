"""Is the answer's error bar honest? Each example as its file is written (only ``seed`` and
``iterations`` change), over seeds and budgets: the final error against the reported standard
error, per job.

    python -m bench.coverage --jobs demo --seeds 0,1,2,3,4 --budgets 1,4
    python -m bench.coverage --jobs hidden-object --recipe default     # its recipe left to the product

A budget is a multiple of the example's ``iterations`` (``1,4`` on the demo: 30 and 120). Per job
and budget the table gives the coverage of ±2 SE (the share of scalars whose truth lies within two
standard errors of the answer: 95% when calibrated), the median |error| / SE (0.67 when calibrated;
under 0.5 the error bars are wide, over 1.0 they are narrow), and the runs that ``stop.auto`` ended
before the cap, with the ratio of their max error to the median max error of the runs that reached
the cap. Results are written after each job and budget, so a run cut short keeps what it measured,
and runs into an existing results file add to it (one budget of a costly job at a time).
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import chosen, machine, markdown_table, write_markdown

log = logging.getLogger("bench.coverage")
ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results" / "coverage.json"
#: The examples with scalar parameters and synthetic targets (a texture's or a mesh's error is not a scalar's).
JOBS = ("demo", "hidden-object", "cornell-red", "bright-room", "pose", "room-open-8", "room-closed-8",
        "room-closed-deep")


def run(job: dict, seed: int, iterations: int) -> dict:
    """One run of ``job`` through the product's loop: its answer, standard errors and stop."""
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_local(JobSpec.model_validate(dict(job, seed=seed, iterations=iterations)), Path(tmp) / "job")
    final, truth = np.asarray(summary["estimate"], float), np.asarray(summary["target_values"], float)
    se = summary.get("standard_error")
    return {"seed": seed, "iterations": iterations, "status": summary["status"], "ran": summary["iterations"],
            "capped": "cap of" in summary["stopped"]["reason"], "stopped": summary["stopped"]["reason"],
            "error": (final - truth).tolist(), "standard_error": se, "run_error": summary.get("run_error"),
            "floor_error": summary.get("floor_error"), "window": summary.get("estimate_window"),
            "seconds": time.perf_counter() - started}


def judge(runs: list[dict]) -> dict:
    """Coverage, median |error| / SE and the auto-stopped runs' errors against the capped runs'."""
    ratios = np.concatenate([np.abs(r["error"]) / np.asarray(r["standard_error"]) for r in runs
                             if r["standard_error"] is not None]) if any(r["standard_error"] for r in runs) else None
    capped = [float(np.max(np.abs(r["error"]))) for r in runs if r["capped"]]
    stopped = [(r["ran"], float(np.max(np.abs(r["error"])))) for r in runs if not r["capped"]]
    reference = float(np.median(capped)) if capped else None
    return {"coverage": None if ratios is None else float(np.mean(ratios <= 2)),
            "median_ratio": None if ratios is None else float(np.median(ratios)),
            "scalars": 0 if ratios is None else int(ratios.size),
            "median_error": float(np.median([np.max(np.abs(r["error"])) for r in runs])),
            "stopped": [{"iterations": n, "error": e, "to_capped": None if not reference else e / reference}
                        for n, e in stopped],
            "seconds": float(sum(r["seconds"] for r in runs))}


def table(results: dict) -> str:
    rows = []
    for name, budgets in results["jobs"].items():
        for entry in budgets.values():
            j = entry["judged"]
            stops = ", ".join(f"{s['iterations']} its ({s['to_capped']:.2f}x)" if s["to_capped"] else
                              f"{s['iterations']} its" for s in j["stopped"]) or "none"
            rows.append([name, entry["iterations"], len(entry["runs"]), j["median_error"],
                         "-" if j["coverage"] is None else f"{100 * j['coverage']:.0f}%",
                         "-" if j["median_ratio"] is None else f"{j['median_ratio']:.2f}", j["scalars"], stops,
                         round(j["seconds"])])
    return markdown_table(["job", "iterations", "seeds", "median max error", "coverage of ±2 SE",
                           "median |error| / SE", "scalars", "stopped early (error / capped runs' median)",
                           "s"], rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", default="demo", help=f"examples, comma-separated (known: {', '.join(JOBS)})")
    parser.add_argument("--seeds", default="0,1,2,3,4")
    parser.add_argument("--budgets", default="1,4", help="multiples of each example's iterations")
    parser.add_argument("--recipe", choices=("file", "default"), default="file",
                        help="run each example as its file is written, or its default job "
                             "(bench.regime.default_job: the recipe left to the product), named "
                             "'<job> (default recipe)'")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    jobs = chosen(args.jobs, JOBS, parser, "job")
    seeds = [int(s) for s in args.seeds.split(",")]
    budgets = [float(b) for b in args.budgets.split(",")]
    if len(seeds) < 1 or any(b <= 0 for b in budgets):
        parser.error("--seeds needs a seed and --budgets positive multiples")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")

    results: dict = {"machine": machine(), "jobs": {}}
    if args.out.exists():            # runs of other jobs and budgets accumulate in one results file
        results["jobs"] = json.loads(args.out.read_text())["jobs"]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for name in jobs:
        job = json.loads((ROOT / "examples" / f"{name}.json").read_text())
        if args.recipe == "default":
            from bench.regime import default_job

            job, name = default_job(job), f"{name} (default recipe)"
        for budget in budgets:
            iterations = max(1, round(budget * job["iterations"]))
            runs = [run(job, seed, iterations) for seed in seeds]
            results["jobs"].setdefault(name, {})[f"{budget:g}"] = {"iterations": iterations, "runs": runs,
                                                                  "judged": judge(runs)}
            args.out.write_text(json.dumps(results, indent=1))
            log.info("%s at %d iterations: %s", name, iterations, results["jobs"][name][f"{budget:g}"]["judged"])
    write_markdown(args.out, "bench.coverage", argv, table(results))
    log.info("wrote %s\n%s", args.out, table(results))


if __name__ == "__main__":
    main()

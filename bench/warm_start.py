"""Warm starts on an experiment's runs: ``seeds x learning rates`` runs of one job, each run cold
(its own warm-up) and warm (``warm_start`` from a first run of the same base), in-process and one
after another. Per run: the seconds from the start of the run (scene, targets, warm-up or top-up
included) to the first iteration whose largest parameter error is at most ``--target-error``,
and the final largest parameter error. The first run's own time is reported apart: a warm start
pays it once per experiment.

    python -m bench.warm_start [--job examples/hidden-object.json] [--seeds 0,1] [--learning-rates 0.04,0.08,0.16]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent


def run(job: dict, folder: Path, name: str, target_error: float) -> dict:
    """One run into ``folder / name``: seconds to ``target_error``, final error, total seconds."""
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    reached: list[float] = []
    started = time.perf_counter()

    def on_event(event: dict) -> None:
        error = event.get("parameter_error") if event.get("type") == "iteration" else None
        if error is not None and error <= target_error and not reached:
            reached.append(time.perf_counter() - started)

    summary = run_local(JobSpec.model_validate(job), folder / name, on_event=on_event)
    seconds = time.perf_counter() - started
    if summary["status"] != "succeeded":
        raise RuntimeError(f"{name}: {summary['status']}: {summary.get('error')}")
    final = float(np.max(np.abs(np.asarray(summary["estimate"]) - np.asarray(summary["target_values"]))))
    plan = json.loads((folder / name / "plan.json").read_text())
    return {"seconds_to_target": reached[0] if reached else None, "final_error": final, "seconds": seconds,
            "warm_start": plan.get("warm_start")}


def measure(job: dict, seeds: list[int], rates: list[float], target_error: float, on_row=None) -> dict:
    """Every run; ``on_row`` sees the partial result after each pair (written as it goes)."""
    folder = Path(tempfile.mkdtemp(prefix="bench-warm-"))
    try:
        first = run(job, folder, "first", target_error)
        rows: list[dict] = []
        for seed in seeds:
            for rate in rates:
                varied = {**job, "seed": seed, "learning_rate": rate}
                cold = run(varied, folder, f"cold-{seed}-{rate}", target_error)
                warm = run({**varied, "warm_start": {"job": "first"}}, folder, f"warm-{seed}-{rate}", target_error)
                rows.append({"seed": seed, "learning_rate": rate, "cold": cold, "warm": warm})
                if on_row is not None:
                    on_row({"first": first, "rows": rows})
                log.info("seed %s lr %s: cold %s / warm %s", seed, rate, cold, warm)
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    return {"first": first, "rows": rows}


def table(result: dict, target_error: float) -> str:
    def cell(v):
        return "not reached" if v is None else v

    lines = [[r["seed"], r["learning_rate"], cell(r["cold"]["seconds_to_target"]), cell(r["warm"]["seconds_to_target"]),
              r["cold"]["final_error"], r["warm"]["final_error"], r["cold"]["seconds"], r["warm"]["seconds"],
              (r["warm"]["warm_start"] or {}).get("top_up_steps")] for r in result["rows"]]
    first = result["first"]
    lines.append(["first run (the source)", "", cell(first["seconds_to_target"]), "", first["final_error"], "",
                  first["seconds"], "", ""])
    return markdown_table(["seed", "learning rate", f"s to {target_error} cold", f"s to {target_error} warm",
                           "final error cold", "final error warm", "s run cold", "s run warm", "top-up steps"], lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.warm_start", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", type=Path, default=ROOT / "examples" / "hidden-object.json")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--learning-rates", default="0.04,0.08,0.16")
    parser.add_argument("--iterations", type=int, default=None, help="override the job's iterations")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    job = json.loads(args.job.read_text())
    if args.iterations is not None:
        job["iterations"] = args.iterations
    job["images_every"] = job["iterations"]
    out = args.out or ROOT / "bench" / "results" / f"warm_start-{args.job.stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    about = machine()

    def write(result: dict) -> None:  # after every pair: a run cut short keeps what it measured
        out.write_text(json.dumps({"machine": about, "job": str(args.job), "target_error": args.target_error,
                                   **result}, indent=1))
        write_markdown(out, "bench.warm_start", argv, table(result, args.target_error))

    result = measure(job, [int(s) for s in args.seeds.split(",")], [float(r) for r in args.learning_rates.split(",")],
                     args.target_error, on_row=write)
    write(result)
    log.info("\n%s", table(result, args.target_error))


if __name__ == "__main__":
    main()

"""Is the answer's standard error calibrated, over enough seeds to tell? (issue 44)

    python -m bench.investigations.calibration --job room-open-8 --resolution 64 --iterations 60 \\
        --seeds 0-48 --label "successive curvature, turning view"

Five seeds of an example as written (``bench.coverage``) give about ten independent errors (a
job's channels move together), too few to tell a standard error 1.3 times too small from bad
luck. This runs a cheaper variant of one example (``--resolution`` overrides the films; every
other field stays as the file writes it) over many seeds and reports the coverage of ±2 SE, the
median |error| / SE (0.67 when calibrated) and, per scalar, the ratio of the errors' root mean
square to the standard errors' (1 when calibrated). ``--label`` names the code the rows measured
(results of several labels sit side by side in ``bench/results/calibration.json``).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown
from bench.coverage import run

log = logging.getLogger("bench.investigations.calibration")
ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "bench" / "results" / "calibration.json"


def judge(runs: list[dict]) -> dict:
    """Coverage of ±2 SE, median |error| / SE, rms(error) / rms(SE) per scalar, median max error."""
    settled = [r for r in runs if r["standard_error"] is not None]
    if not settled:
        return {"runs": len(runs), "settled": 0}
    error = np.array([r["error"] for r in settled])
    se = np.array([r["standard_error"] for r in settled])
    ratio = np.abs(error) / se
    return {"runs": len(runs), "settled": len(settled), "coverage": float(np.mean(ratio <= 2)),
            "median_ratio": float(np.median(ratio)),
            "rms_ratio": (np.sqrt((error ** 2).mean(0)) / np.sqrt((se ** 2).mean(0))).tolist(),
            "median_max_error": float(np.median(np.abs(error).max(1)))}


def table(results: dict) -> str:
    rows = []
    for key, entry in results["variants"].items():
        j = judge(entry["runs"])
        rows.append([key.split(": ")[0], entry["label"], f"{j['settled']} / {j['runs']}", f"{j.get('coverage', 0):.0%}",
                     f"{j.get('median_ratio', float('nan')):.2f}",
                     ", ".join(f"{v:.2f}" for v in j.get("rms_ratio", [])), f"{j.get('median_max_error', 0):.3g}"])
    return markdown_table(["job", "code", "runs with SE", "±2 SE", "median |error|/SE",
                           "rms(error)/rms(SE) per scalar", "median max error"], rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--job", default="room-open-8", help="an example of examples/")
    parser.add_argument("--resolution", type=int, default=64, help="the films' width and height (0: as written)")
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--seeds", default="0-48", help="a range a-b (b excluded)")
    parser.add_argument("--label", required=True, help="what code the runs measure")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    job = json.loads((ROOT / "examples" / f"{args.job}.json").read_text())
    if args.resolution:
        job["render"] = dict(job.get("render", {}), resolution=[args.resolution, args.resolution])
    first, last = (int(s) for s in args.seeds.split("-"))
    results = json.loads(args.out.read_text()) if args.out.exists() else {"machine": machine(), "variants": {}}
    films = f"{args.resolution}x{args.resolution}" if args.resolution else "films as written"
    key = f"{args.job} {films}, {args.iterations} its: {args.label}"
    entry = results["variants"].setdefault(key, {"label": args.label, "runs": []})
    done = {r["seed"] for r in entry["runs"]}
    for seed in range(first, last):
        if seed in done:
            continue
        entry["runs"].append(run(job, seed, args.iterations))
        args.out.write_text(json.dumps(results, indent=1))   # after each run: a run cut short keeps what it measured
    log.info("%s: %s", key, judge(entry["runs"]))
    write_markdown(args.out.with_suffix(".md"), "bench.investigations.calibration", argv, table(results))


if __name__ == "__main__":
    main()

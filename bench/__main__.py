"""``python -m bench [--quick] [--parts ...]``: what accuracy costs in time, in one run.

Parts (all by default, in this order): ``accuracy`` (gradient error vs wall time per method on
cornell-box, hidden-object and glossy-box), ``depth`` (iteration cost vs path length, prb vs
ndrf-rhs), ``scaling`` (training-step time and memory vs number of scalars), ``e2e`` (parameter
error vs time of whole jobs on the hidden object), ``effects`` (what the chosen effects save). Results, tables and plots go
to
``bench/results/`` (``--quick`` writes ``bench/results/quick/``), with the machine described.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

PARTS = ("accuracy", "depth", "scaling", "effects", "e2e")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="smaller grids: under 10 minutes on 2 cores")
    parser.add_argument("--parts", default=",".join(PARTS), help=f"comma-separated subset of {', '.join(PARTS)}")
    parser.add_argument("--out", type=Path, default=None, help="results folder")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    parts = [p.strip() for p in args.parts.split(",") if p.strip()]
    unknown = set(parts) - set(PARTS)
    if unknown:
        parser.error(f"unknown parts {sorted(unknown)}; known: {', '.join(PARTS)}")
    out = args.out or Path(__file__).parent / "results" / ("quick" if args.quick else "")
    out.mkdir(parents=True, exist_ok=True)

    from bench import accuracy_time, depth, effects_savings, end_to_end, report, scaling
    from bench.common import machine, markdown_table

    modules = {"accuracy": accuracy_time, "depth": depth, "scaling": scaling, "effects": effects_savings,
               "e2e": end_to_end}
    results, seconds = {"machine": machine(), "quick": args.quick}, {}
    for part in parts:
        start = time.perf_counter()
        results[part] = modules[part].run(args.quick)
        seconds[part] = time.perf_counter() - start
        (out / "results.json").write_text(json.dumps(results, indent=2))
    results["seconds"] = seconds
    (out / "results.json").write_text(json.dumps(results, indent=2))

    sections = [f"# Benchmark results{' (quick)' if args.quick else ''}", "",
                "Machine: " + ", ".join(f"{k} {v}" for k, v in results["machine"].items()),
                f"Command: `python -m bench{' --quick' if args.quick else ''} --parts {','.join(parts)}`; "
                f"wall time per part: " + ", ".join(f"{p} {s:.0f} s" for p, s in seconds.items()), ""]
    if "accuracy" in results:
        report.accuracy_plot(results["accuracy"], out / "accuracy.png")
        sections += ["## Gradient error against time", "", "![accuracy](accuracy.png)", "",
                     report.accuracy_table(results["accuracy"]), ""]
    if "depth" in results:
        report.depth_plot(results["depth"], out / "depth.png")
        sections += ["## Iteration cost against path length", "", "![depth](depth.png)", "",
                     report.depth_table(results["depth"]), ""]
    if "scaling" in results:
        report.scaling_plot(results["scaling"], out / "scaling.png")
        sections += ["## Training cost against the number of optimized scalars", "", "![scaling](scaling.png)", "",
                     report.scaling_table(results["scaling"]), ""]
    if "effects" in results:
        rows = [[r["case"], r["unit"], r["planned"], r["everything on"], f"{100 * r['saving']:.0f}%"]
                for r in results["effects"]["rows"]]
        sections += ["## What the chosen effects save", "",
                     markdown_table(["case", "unit", "planned", "everything on", "saving"], rows), ""]
    if "e2e" in results:
        report.e2e_plot(results["e2e"], out / "e2e.png")
        sections += ["## Inverse rendering of the hidden object, error against time", "", "![e2e](e2e.png)", "",
                     report.e2e_table(results["e2e"]), ""]
    (out / "report.md").write_text("\n".join(sections))
    logging.getLogger("bench").info("\n%s", "\n".join(sections))


if __name__ == "__main__":
    main()

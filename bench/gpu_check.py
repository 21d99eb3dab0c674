"""The prepared device check (issue 35): the example jobs and the methods' seconds per iteration on
the device ``NDRF_DEVICE`` names, with the CPU's figures beside them.

``NDRF_DEVICE=cuda python -m bench.gpu_check --out OUT.json [--cpu bench/results/gpu_check-cpu.json]
[--iterations 10] [--budget 60] [--deadline 300] [--tests-log FILE]``

``bench/gpu_check.sh`` runs it after the device's unit tests, in one call of the lent machine;
``NDRF_DEVICE=cpu`` here gives the CPU column (``bench/results/gpu_check-cpu.json``). In one process,
on one device:

1. ``jobs``: ``examples/demo.json``, ``room-open-8.json`` and ``hidden-object.json`` as a user runs
   them (``ndrf run``'s :func:`services.jobs.local.run_local`), each stopped after ``--budget``
   seconds: status, iterations, the median seconds per iteration, seconds to a max parameter error
   of 0.02 (decision time included, :func:`bench.regime.run_product`'s clock) and the final error.
2. ``methods``: seconds per iteration of ``prb``, ``ndrf-lhs`` and ``ndrf-rhs`` (each the job's
   other defaults) on the demo job, the median of ``--iterations`` iterations from the initial
   values, and of Mitsuba's tutorial loop on the same job (:func:`bench.mitsuba_loop.run_loop`:
   ``prb``, 1 spp, Russian roulette from depth 5, its one view). The NDRF methods' warm-up is
   shortened to 20 training steps (an iteration's own ``steps_per_iteration`` are unchanged; the
   median leaves the first iterations' kernel compilation out).

Items start only while ``--deadline`` seconds have not passed; the file is rewritten after each
one, so a call cut short still returns what it measured. One JSON (the machine and its device, the
rows, ``--cpu``'s rows beside them, ``--tests-log``'s tail) and a markdown table of the same name.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time
from pathlib import Path

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
JOBS = ("demo", "room-open-8", "hidden-object")
METHODS = ("prb", "ndrf-lhs", "ndrf-rhs")
SHORT_WARMUP = {"training": {"warmup_steps": 20}}


def _job(name: str) -> dict:
    return json.loads((ROOT / "examples" / f"{name}.json").read_text())


def job_row(name: str, budget: float) -> dict:
    from bench.regime import run_product

    start = time.perf_counter()
    run = run_product(_job(name), 0.02, budget=budget)
    return {"status": str(getattr(run["status"], "value", run["status"])), "iterations": run["iterations"],
            "wall_seconds": time.perf_counter() - start,
            "seconds_per_iteration": run["seconds_per_iteration"],
            "seconds_to_0.02": run["reached"]["seconds"] if run["reached"] else None,
            "final_error": run["final_error"], "method": run["recipe"].get("method")}


def method_row(method: str, iterations: int) -> dict:
    from bench.regime import merge, run_product

    job = merge(_job("demo"), {"method": method, **SHORT_WARMUP})
    start = time.perf_counter()
    run = run_product(job, 0.02, iterations=iterations)
    return {"seconds_per_iteration": run["seconds_per_iteration"], "iterations": run["iterations"],
            "status": str(getattr(run["status"], "value", run["status"])), "final_error": run["final_error"],
            "wall_seconds": time.perf_counter() - start}


def loop_row(iterations: int) -> dict:
    from bench.common import loop_rows
    from bench.mitsuba_loop import LoopSetting, run_loop

    setting = LoopSetting(spp=1, rr_depth=5, views=None)
    start = time.perf_counter()
    run, _ = loop_rows(_job("demo"), lambda prepared: run_loop(prepared, setting, target_error=0.0,
                                                               iterations=iterations))
    return {"seconds_per_iteration": run["seconds_per_iteration"], "iterations": run["iterations"],
            "setting": run["setting"], "final_error": run["final_error"],
            "wall_seconds": time.perf_counter() - start}


def table(result: dict) -> str:
    from bench.common import markdown_table

    device = result["machine"].get("device", "?")
    cpu = result.get("cpu") or {}
    header = ["what", f"s / iteration ({device})", "s / iteration (cpu)", f"cpu / {device}", "status", "iterations",
              "s to 0.02", "final error"]

    def row(label, mine, theirs):
        if mine is None:
            return [label, "not run", "", "", "", "", "", ""]
        if "error" in mine:
            return [label, "failed", "", "", mine["error"][:80], "", "", ""]
        a = mine.get("seconds_per_iteration")
        b = (theirs or {}).get("seconds_per_iteration")
        ratio = f"{b / a:.1f}x" if a and b else ""
        reach = mine.get("seconds_to_0.02")
        return [label, f"{a:.4f}" if a else "-", f"{b:.4f}" if b else "-", ratio, mine.get("status", ""),
                mine.get("iterations", ""), f"{reach:.2f}" if reach is not None else "-",
                f"{mine['final_error']:.4f}" if mine.get("final_error") is not None else "-"]

    rows = [row(f"job {n}", result["jobs"].get(n), cpu.get("jobs", {}).get(n)) for n in JOBS]
    rows += [row(f"demo, method {m}", result["methods"].get(m), cpu.get("methods", {}).get(m)) for m in METHODS]
    rows.append(row("demo, Mitsuba's tutorial loop", result["methods"].get("loop"), cpu.get("methods", {}).get("loop")))
    return markdown_table(header, rows)


def _write(out: Path, result: dict) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(result, indent=1))
    machine = result["machine"]
    stamp = ", ".join(f"{k} {v}" for k, v in machine.items() if v is not None and not isinstance(v, dict))
    load = ", ".join(f"{k} {v[0]:.1f}" for k, v in result["load_average"].items())
    out.with_suffix(".md").write_text(f"Machine: {stamp}\nCommand: `{result['command']}`\n\n{table(result)}\n\n"
                                      f"Load average (1 min) at the {load}.\n")


def run(out: Path, *, cpu: Path | None, iterations: int, budget: float, deadline: float,
        tests_log: Path | None) -> dict:
    from bench.common import machine

    started = time.perf_counter()
    result: dict = {"machine": machine(), "command": "NDRF_DEVICE={} python -m bench.gpu_check".format(
        os.environ.get("NDRF_DEVICE", "auto")), "jobs": {}, "methods": {}, "skipped": [],
        "load_average": {"start": list(os.getloadavg())}}   # other processes on the machine slow every figure
    if cpu is not None and cpu.exists():
        saved = json.loads(cpu.read_text())
        result["cpu"] = {"machine": saved["machine"], "jobs": saved["jobs"], "methods": saved["methods"]}
    if tests_log is not None and tests_log.exists():
        result["tests"] = tests_log.read_text()[-4000:]
    items = [("jobs", n, lambda n=n: job_row(n, budget)) for n in JOBS]
    items += [("methods", m, lambda m=m: method_row(m, iterations)) for m in METHODS]
    items.append(("methods", "loop", lambda: loop_row(iterations)))
    for group, name, measure in items:
        if time.perf_counter() - started > deadline:
            result["skipped"].append(f"{group}/{name}")
            log.warning("%s/%s skipped: past the %.0f s deadline", group, name, deadline)
            continue
        log.info("%s/%s ...", group, name)
        try:
            result[group][name] = measure()
        except Exception as exc:  # one failure must not hide the rest of the check
            log.exception("%s/%s failed", group, name)
            result[group][name] = {"error": f"{type(exc).__name__}: {exc}"}
        log.info("%s/%s: %s", group, name, result[group][name])
        result["seconds"] = time.perf_counter() - started
        result["load_average"]["end"] = list(os.getloadavg())
        _write(out, result)
    return result


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.gpu_check", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, required=True, help="the results file (.json; a .md beside it)")
    parser.add_argument("--cpu", type=Path, default=None, help="an earlier NDRF_DEVICE=cpu run's file, shown beside")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--budget", type=float, default=60.0, help="seconds per example job")
    parser.add_argument("--deadline", type=float, default=300.0, help="no item starts after this many seconds")
    parser.add_argument("--tests-log", type=Path, default=None, help="the device's unit-test output, kept in the file")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    from services.solver.backend import describe_device, use_mitsuba, use_torch

    use_mitsuba(), use_torch()
    log.info("device: %s", describe_device())
    result = run(args.out, cpu=args.cpu, iterations=args.iterations, budget=args.budget, deadline=args.deadline,
                 tests_log=args.tests_log)
    log.info("\n%s", table(result))


if __name__ == "__main__":
    main()

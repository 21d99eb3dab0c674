"""The product's recipes against the loop a user writes instead, on one job, in one process.

``python -m bench.regime --job examples/room-open-8.json [--variants default,adam,...] [--budget 60]``

Every row is the same problem: the job's scene, initial values, bounds and targets
(``prepare``). The loop rows are :mod:`bench.mitsuba_loop`'s grid (Mitsuba's tutorial loop with
``prb``); the product rows are the job through ``run_local`` (the product's own loop, records and
files included) with the changes of :data:`VARIANTS`. ``default`` is the job with only its scene,
parameters, targets, iterations and film (:func:`default_job`): what a user gets without tuning
anything.

Clock. Scene loading and target rendering are outside it for everyone. The loop's clock starts at
its first iteration. The product's adds the seconds spent deciding (the effect probe and the depth
check and the recipe's own measurements of the scene: ``plan.json``'s ``prepared_seconds.resolve``)
to the time from the plan report
to each iteration's record, so writing targets and records counts against it. Every row runs once
untimed for two iterations first, so that no row pays Dr.Jit's kernel compilation and another
not. Reported: seconds per iteration (median), when the largest parameter error first falls below
``--target-error`` and from when it stays below, the final error, and the ratio of each row's time
to the best loop's.

One scene at a time: the loop's prepared scene is freed before the product's rows run
(:func:`bench.common.loop_rows`), as each product run frees its own.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import chosen, loop_rows, machine, markdown_table, write_markdown
from bench.mitsuba_loop import best, grid, run_grid

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent

#: the fields a default job keeps: the problem as the example states it (its film included), none
#: of its recipe
DEFAULT_FIELDS = ("scene", "parameters", "targets", "iterations")

#: name -> changes to the default job
VARIANTS: dict[str, dict] = {
    "default": {},
    "prb": {"method": "prb"},         # the open scenes' auto recipe, forced
    "ndrf": {"method": "ndrf-lhs"},   # the closed scenes' auto recipe, forced
    "adam": {"method": "prb", "optimizer": "adam"},
    "gauss-newton": {"method": "prb", "optimizer": "gauss-newton"},
    "levenberg-marquardt-lr-0.2": {"method": "prb", "optimizer": "levenberg-marquardt", "learning_rate": 0.2},
    "levenberg-marquardt-all-views": {"method": "prb", "optimizer": "levenberg-marquardt", "views_per_iteration": 8},
    "hybrid": {"method": "prb", "optimizer": "levenberg-marquardt", "jacobian": "differential-field",
               "training": {"warmup_steps": 100, "steps_per_iteration": 4}},
    "ndrf-lhs-levenberg-marquardt": {"method": "ndrf-lhs", "optimizer": "levenberg-marquardt",
                                     "render": {"first_hits": "cached"},
                                     "training": {"warmup_steps": 100, "steps_per_iteration": 4}},
}


def default_job(job: dict) -> dict:
    """The example ``job`` with only what a user must state: :data:`DEFAULT_FIELDS` and the film
    (``render.resolution``: the targets' size is the problem's, not a choice of the recipe; before,
    the demo ran at the scene's 256x256 where its file says 64x64)."""
    out = {key: job[key] for key in DEFAULT_FIELDS if key in job}
    resolution = (job.get("render") or {}).get("resolution")
    if resolution is not None:
        out["render"] = {"resolution": resolution}
    return out


def dropped(job: dict) -> list[str]:
    """What :func:`default_job` leaves out of an example's file (its recipe's choices), as
    ``key`` or ``render.key``: a row that runs the default job names them, since it does not run
    the file as written."""
    kept = default_job(job)
    out = [key for key in job if key not in kept and key not in ("name", "seed", "render")]
    out += [f"render.{key}" for key in (job.get("render") or {}) if key != "resolution"]
    return sorted(out)


def merge(base: dict, change: dict) -> dict:
    out = dict(base)
    for key, value in change.items():
        out[key] = merge(base.get(key, {}), value) if isinstance(value, dict) else value
    return out


def run_product(job: dict, target_error: float, budget: float | None = None, iterations: int | None = None) -> dict:
    """One job through the product's loop; the error curve on the clock of the module docstring.
    The run's scene is freed before this returns (:func:`bench.common.loop_rows`)."""
    import gc

    from schemas.job import JobSpec
    from services.jobs.local import run_local

    gc.collect()
    if iterations is not None:
        job = dict(job, iterations=iterations)
    events: list[tuple[float, dict]] = []
    with tempfile.TemporaryDirectory() as tmp:

        def stop() -> str | None:  # the budget runs from the plan: target rendering is outside it
            return "canceled" if budget is not None and events and time.perf_counter() - events[0][0] > budget else None

        def on_event(event: dict) -> None:
            if event.get("type") in ("plan", "iteration"):
                events.append((time.perf_counter(), event))

        summary = run_local(JobSpec.model_validate(job), Path(tmp) / "job", on_event=on_event, should_stop=stop)
        plan = json.loads((Path(tmp) / "job" / "plan.json").read_text())
    gc.collect()
    planned = next(t for t, e in events if e["type"] == "plan")
    decided = plan["prepared_seconds"]["resolve"]
    curve = [{"iteration": e["iteration"], "seconds": decided + t - planned, "error": e["parameter_error"],
              "views": e["views"]} for t, e in events if e["type"] == "iteration"]
    reached = next((c for c in curve if c["error"] < target_error), None)
    steps = np.diff([decided] + [c["seconds"] for c in curve])
    return {"status": summary["status"], "curve": curve, "reached": reached,
            "final_error": curve[-1]["error"] if curve else None, "iterations": len(curve),
            "seconds_per_iteration": float(np.median(steps)) if len(steps) else None, "recipe": plan["recipe"]}


def stays_below(curve: list[dict], target_error: float) -> dict | None:
    """The first point of ``curve`` after which the error stays below ``target_error`` to the end."""
    for i, point in enumerate(curve):
        if all(c["error"] < target_error for c in curve[i:]):
            return point
    return None


def race(job: dict, variants: list[str] | dict[str, dict], *, target_error: float, budget: float | None,
         loop_spp: list[int], loop_rr: list[int | None], loop_views: list[int | None]) -> dict:
    """The loop's grid and the product's variants on ``job`` (names of :data:`VARIANTS`, or rows
    with their own changes); results by row name."""
    base = default_job(job)

    def loop_grid(prepared) -> dict[str, dict]:
        views = [v for v in loop_views if v is None or v < len(prepared.targets)] or [None]
        return run_grid(prepared, grid(loop_spp, loop_rr, views), target_error=target_error, budget=budget)

    rows, _ = loop_rows(base, loop_grid)   # the loop's scene is freed before the product's runs
    changes = variants if isinstance(variants, dict) else {name: VARIANTS[name] for name in variants}
    for name, change in changes.items():
        variant = merge(base, change)
        compile_only = {"targets": {"synthetic": {"spp": 1}}, "training": {"warmup_steps": 2}}
        run_product(merge(variant, compile_only), target_error, iterations=2)   # its kernels, untimed
        log.info("product: %s", name)
        rows[name] = run_product(variant, target_error, budget)
    return rows


def table(rows: dict[str, dict], target_error: float) -> str:
    found = best({k: v for k, v in rows.items() if k.startswith("loop")})
    reference = found[1]["reached"]["seconds"] if found else None
    lines = []
    for name, r in rows.items():
        reached, stays = r["reached"], stays_below(r["curve"], target_error)
        ratio = f"{reached['seconds'] / reference:.2f}x" if reached and reference else "-"
        if found and name == found[0]:
            ratio = "1 (best loop)"
        per_iteration = r["seconds_per_iteration"]
        lines.append([name, f"{per_iteration:.3f}" if per_iteration is not None else "-",
                      f"{reached['seconds']:.2f} s (it. {reached['iteration']})" if reached else "not reached",
                      ratio, f"{stays['seconds']:.1f} s" if stays else "-",
                      f"{r['final_error']:.4f} after {r['iterations']}" if r["curve"] else
                      f"no iteration within the budget ({r['status']})"])
    return markdown_table(["row", "s / iteration", f"first max error < {target_error}", "time / best loop's",
                           "stays below from", "final max error"], lines)


def _values(text: str, parse) -> list:
    return [parse(v.strip()) for v in text.split(",") if v.strip()]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.regime", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", type=Path, required=True, help="a job file with synthetic targets")
    parser.add_argument("--variants", default="default,adam", help=f"subset of {', '.join(VARIANTS)}")
    parser.add_argument("--loop-spp", default="1,4")
    parser.add_argument("--loop-rr", default="5,off")
    parser.add_argument("--loop-views", default="1,2,4,all")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--budget", type=float, default=60.0,
                        help="stop each row after this many seconds (the product's from its plan report)")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    job = json.loads(args.job.read_text())
    rows = race(job, chosen(args.variants, VARIANTS, parser, "variant"), target_error=args.target_error,
                budget=args.budget, loop_spp=_values(args.loop_spp, int),
                loop_rr=_values(args.loop_rr, lambda v: None if v == "off" else int(v)),
                loop_views=_values(args.loop_views, lambda v: None if v == "all" else int(v)))
    out = args.out or ROOT / "bench" / "results" / f"regime-{args.job.stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine(), "job": str(args.job), "target_error": args.target_error,
                               "rows": rows}, indent=1))
    text = table(rows, args.target_error)
    write_markdown(out, "bench.regime", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

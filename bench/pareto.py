"""Accuracy against time, measured on what a user takes home: the final answer of a run at a
budget, for the default job and for the best Mitsuba tutorial loop given the same time.

``python -m bench.pareto [--jobs demo,room-open-8,room-closed-8,hidden-object,textured-box]
[--seeds 0,1,2] [--budgets 0.5,1,2,4] [--loop-views 1,2,all|none] [--variant NAME]
[--out bench/results/pareto.json] [--reuse-default] [--report-only]``

For each job of ``examples/`` (reduced to its scene, parameters, targets, iterations and film:
what a user sets, :func:`bench.regime.default_job`) and each budget ``m``, the default job runs
``m x`` the example's iterations, once per seed (its targets rendered from that seed), through
``run_local`` (the product's loop, records and files included). Its answer is ``summary.json``'s
``final`` (the estimate), its time the
compute seconds on :mod:`bench.regime`'s clock (the decisions' measurements included, target
rendering excluded). A run may end before its iterations (``stop.auto``): its time is what it
took.

The loop is :mod:`bench.mitsuba_loop`'s tutorial loop (``prb``, 1 spp, Russian roulette from depth
5, Adam (0.8, 0.99) with the learning rate decaying from the job's 0.05 to 0.005 over the run),
with ``v`` random views per iteration for each ``v`` of ``--loop-views``, on the same targets.
Each setting plans as many iterations as fit in the default job's median time at that budget
(its seconds per iteration measured on a short run first, then on the previous budget's run: an
iteration costs more as a bright room's albedos rise), its learning rate decaying over them, is
cut at twice that time, and returns its last iterate: the user's answer. The best loop at a
budget is the setting with the smallest median error there.

``--variant NAME`` (a :data:`bench.regime.VARIANTS` change: ``prb`` or ``ndrf`` force the method
``auto`` takes in open or in closed scenes; ``other``, per budget, the one of the two that
``auto`` did not take there) runs beside the default at the default's seconds: it
plans as many iterations as fit in the default's median seconds at each budget, from its fixed
seconds (deciding and, for a field, the warm-up) and its seconds per iteration, measured on a
probe run of :data:`PROBE_ITERATIONS` first and then on the previous budget's runs, and is stopped
at those seconds if it has not ended by then (a prb iteration costs more as a closed room's
albedos rise, which a short probe does not see). Its answer is its own ``final`` (the estimate it
had when it ended), as the default's.

Error: the largest ``|p - truth|`` over the scalars; for a texture job the RMSE over its texels
(a texel's worst error is noise). Reported per job and budget: the median and the range over the
seeds of both, their seconds, whether the default's error ever grew with the budget (seed by
seed), and the coverage of ``±2`` standard errors with the median ``|error| / SE`` (a calibrated
Gaussian gives 95% and 0.67). ``bench/results/pareto.png`` plots error against seconds.
"""

from __future__ import annotations

import argparse
import gc
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown
from bench.mitsuba_loop import LoopSetting, run_loop
from bench.regime import VARIANTS, default_job, dropped, merge

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
JOBS = ("demo", "room-open-8", "room-closed-8", "hidden-object", "textured-box")
#: Iterations of the probe run that measures a variant's seconds before its budgets are planned.
PROBE_ITERATIONS = 6


def error_of(values, truth, texture: bool) -> float:
    difference = np.asarray(values, np.float64) - np.asarray(truth, np.float64)
    return float(np.sqrt(np.mean(difference ** 2)) if texture else np.max(np.abs(difference)))


def run_default(job: dict, seed: int, iterations: int, change: dict | None = None,
                budget: float | None = None) -> dict:
    """The default job with ``iterations`` and ``seed`` (and the :data:`bench.regime.VARIANTS`-style
    ``change``, when given): its answer, standard errors and seconds. With ``budget``, the run is
    stopped (canceled) once its clock passes that many seconds, and its answer is the estimate it
    had then."""
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    gc.collect()
    events: list[tuple[float, dict]] = []
    spec = JobSpec.model_validate(merge({**default_job(job), "iterations": iterations, "seed": seed}, change or {}))
    with tempfile.TemporaryDirectory() as tmp:
        def on_event(event: dict) -> None:
            if event.get("type") in ("plan", "iteration"):
                events.append((time.perf_counter(), event))

        def stop() -> str | None:   # the clock runs from the plan: target rendering is outside it
            planned = next((t for t, e in events if e["type"] == "plan"), None)
            late = budget is not None and planned is not None and time.perf_counter() - planned > budget
            return "canceled" if late else None

        summary = run_local(spec, Path(tmp) / "job", on_event=on_event, should_stop=stop)
        plan = json.loads((Path(tmp) / "job" / "plan.json").read_text())
        texture = None
        for key, files in (summary.get("textures") or {}).items():
            final = np.load(Path(tmp) / "job" / files["npy"])
            target = np.load(Path(tmp) / "job" / files["target"])
            errors, last = files.get("standard_error"), files.get("last")
            texture = {"key": key, "final": final, "target": target,
                       "se": np.load(Path(tmp) / "job" / errors) if errors else None,
                       "last": np.load(Path(tmp) / "job" / last) if last else None}
    gc.collect()
    planned = next(t for t, e in events if e["type"] == "plan")
    last = max(t for t, e in events if e["type"] == "iteration")
    seconds = plan["prepared_seconds"]["resolve"] + last - planned
    first = min(t for t, e in events if e["type"] == "iteration")
    fixed = plan["prepared_seconds"]["resolve"] + first - planned   # to the first iteration's record
    per_iteration = (last - first) / max(summary["iterations"] - 1, 1)
    out = {"seed": seed, "iterations": summary["iterations"], "seconds": seconds, "status": summary["status"],
           "fixed_seconds": fixed, "seconds_per_iteration": per_iteration, "method": plan["recipe"].get("method"),
           "stopped": (summary.get("stopped") or {}).get("reason"),
           "estimate": {"kind": summary.get("estimate_kind"), "window": summary.get("estimate_window")}}
    if texture is not None:
        out["error"] = error_of(texture["final"], texture["target"], True)
        if texture["last"] is not None:
            out["last_error"] = error_of(texture["last"], texture["target"], True)
        if texture["se"] is not None:
            out["z"] = (np.abs(texture["final"] - texture["target"]) / np.maximum(texture["se"], 1e-12)).ravel().tolist()
    else:
        out["error"] = error_of(summary["estimate"], summary["target_values"], False)
        out["last_error"] = error_of(summary["last_iterate"], summary["target_values"], False)
        if summary.get("standard_error"):
            se = np.asarray(summary["standard_error"])
            out["z"] = (np.abs(np.asarray(summary["estimate"]) - summary["target_values"]) / np.maximum(se, 1e-12)).tolist()
            out["standard_error"] = se.tolist()
    return out


#: ``--variant other``: per budget, the method ``auto`` did not choose there (its recipe otherwise auto)
OTHER = "other"


def _change(variant: str, default_runs: list[dict]) -> tuple[str, dict]:
    """The variant's label and job change at one budget: a :data:`bench.regime.VARIANTS` entry, or
    for :data:`OTHER` the method of ``prb`` and ``ndrf-lhs`` that the default's runs did not use."""
    if variant != OTHER:
        return variant, VARIANTS[variant]
    other = "prb" if all(r.get("method") == "ndrf-lhs" for r in default_runs) else "ndrf-lhs"
    return other, {"method": other}


def run_variant(job: dict, seeds: list[int], variant: str, defaults: dict[str, list[dict]],
                seconds: dict[float, float]) -> dict:
    """The job with the variant's change at each budget's time (``seconds`` by budget, module
    docstring): per budget, its label and one run per seed. A change is probed once, on its
    first budget; a later budget plans from the previous runs of the same change."""
    rates: dict[str, tuple[float, float]] = {}   # label -> (fixed seconds, seconds per iteration)
    out: dict = {}
    for budget, target in seconds.items():
        label, change = _change(variant, defaults[str(budget)])
        if label not in rates:
            probe = run_default(job, seeds[0], PROBE_ITERATIONS, change)
            rates[label] = probe["fixed_seconds"], probe["seconds_per_iteration"]
        fixed, per_iteration = rates[label]
        iterations = max(2, 1 + int(round((target - fixed) / per_iteration)))
        runs = [run_default(job, seed, iterations, change, budget=target) for seed in seeds]
        for run in runs:
            log.info("variant %s budget %s seed %d: %d iterations, %.1f s (default %.1f s), error %.4g", label,
                     budget, run["seed"], run["iterations"], run["seconds"], target, run["error"])
        out[str(budget)] = [{**run, "variant": label} for run in runs]
        rates[label] = (float(np.median([r["fixed_seconds"] for r in runs])),
                        float(np.median([r["seconds_per_iteration"] for r in runs])))
    return out


def run_loops(job: dict, seed: int, views: list[int | None], seconds: dict[float, float], texture: bool) -> dict:
    """Each view setting at each budget's time (``seconds`` by budget): the last iterate's error."""
    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare

    gc.collect()
    prepared, _ = prepare(JobSpec.model_validate({**default_job(job), "seed": seed}))
    truth = prepared.target_values
    out: dict = {}
    try:
        for v in views:
            setting = LoopSetting(1, 5, v)
            run_loop(prepared, setting, target_error=0.0, iterations=2, seed=seed)            # compile, untimed
            probe = run_loop(prepared, setting, target_error=0.0, iterations=10, seed=seed)
            per_iteration = probe["curve"][-1]["seconds"] / len(probe["curve"])
            for budget, target_seconds in seconds.items():
                # the learning rate decays over the iterations the loop plans, as a user's would; an
                # iteration's cost grows as the albedos brighten (longer paths), so each budget plans
                # with the rate the previous one measured, and a run is cut at twice its time
                total = max(2, int(round(target_seconds / per_iteration)))
                result = run_loop(prepared, setting, target_error=0.0, iterations=total, seed=seed, truth=truth,
                                  budget=2.0 * target_seconds)
                per_iteration = result["curve"][-1]["seconds"] / len(result["curve"])
                final = result["curve"][-1]
                out.setdefault(setting.label, {})[str(budget)] = {
                    "iterations": total, "seconds": final["seconds"],
                    "error": final["rmse"] if texture else final["error"]}
                log.info("loop %s seed %d budget %s: %d iterations, %.1f s, error %.4g", setting.label, seed, budget,
                         total, final["seconds"], out[setting.label][str(budget)]["error"])
    finally:
        del prepared
        gc.collect()
    return out


def summarize(name: str, rows: dict) -> tuple[list[list], dict]:
    """Table rows per budget and the job's checks (monotone, coverage)."""
    table, checks = [], {}
    budgets = sorted(rows["default"], key=float)

    def spread(errors: list[float]) -> str:
        return f"{np.median(errors):.4f} ({min(errors):.4f}-{max(errors):.4f})"

    for budget in budgets:
        runs = rows["default"][budget]
        errors = [r["error"] for r in runs]
        seconds = [r["seconds"] for r in runs]
        row = [name, budget, spread(errors), f"{np.median(seconds):.1f}"]
        if rows.get("loops"):
            loops = {label: [rows["loops"][str(seed)][label][budget] for seed in rows["loops"]]
                     for label in next(iter(rows["loops"].values()))}
            best_label = min(loops, key=lambda label: np.median([r["error"] for r in loops[label]]))
            best = [r["error"] for r in loops[best_label]]
            row += [spread(best), f"{np.median([r['seconds'] for r in loops[best_label]]):.1f}", best_label[5:],
                    "yes" if np.median(errors) <= np.median(best) else "no"]
        else:
            row += ["-"] * 4
        variant = (rows.get("variant") or {}).get("runs", {}).get(budget)
        if variant:
            theirs = [r["error"] for r in variant]
            label = variant[0].get("variant", rows["variant"]["name"])
            row += [f"{label}: {spread(theirs)}", f"{np.median([r['seconds'] for r in variant]):.1f}",
                    "yes" if np.median(errors) <= np.median(theirs) else "no"]
        else:
            row += ["-"] * 3
        table.append(row)
    per_seed = {}
    for i in range(len(rows["default"][budgets[0]])):
        sequence = [rows["default"][b][i]["error"] for b in budgets]
        per_seed[rows["default"][budgets[0]][i]["seed"]] = sequence
    medians = [float(np.median([r["error"] for r in rows["default"][b]])) for b in budgets]
    z = [v for b in budgets for r in rows["default"][b] for v in r.get("z") or []]
    checks = {"medians": medians, "median_never_worse": all(b <= a * 1.0001 for a, b in zip(medians, medians[1:])),
              "per_seed": per_seed,
              "coverage_2se": float(np.mean(np.asarray(z) <= 2)) if z else None,
              "median_z": float(np.median(z)) if z else None, "scalars": len(z)}
    return table, checks


def plot(results: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = list(results)
    fig, axes = plt.subplots(1, len(names), figsize=(4 * len(names), 3.6), squeeze=False)
    for ax, name in zip(axes[0], names):
        rows = results[name]
        budgets = sorted(rows["default"], key=float)
        curves = [("default job", "C0", rows["default"])]
        if rows.get("variant"):
            curves.append((f"variant {rows['variant']['name']}", "C5", rows["variant"]["runs"]))
        for label, color, runs in curves:
            xs = [np.median([r["seconds"] for r in runs[b]]) for b in budgets]
            ys = [np.median([r["error"] for r in runs[b]]) for b in budgets]
            lo = [min(r["error"] for r in runs[b]) for b in budgets]
            hi = [max(r["error"] for r in runs[b]) for b in budgets]
            ax.errorbar(xs, ys, yerr=[np.subtract(ys, lo), np.subtract(hi, ys)], marker="o", color=color, label=label,
                        capsize=3)
        labels = list(next(iter(rows["loops"].values()))) if rows.get("loops") else []
        for n, label in enumerate(labels):
            xs = [np.median([rows["loops"][s][label][b]["seconds"] for s in rows["loops"]]) for b in budgets]
            ys = [np.median([rows["loops"][s][label][b]["error"] for s in rows["loops"]]) for b in budgets]
            ax.plot(xs, ys, marker="s", linestyle="--", color=f"C{n + 1}", label=label.replace("loop ", "loop: "))
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(name)
        ax.set_xlabel("seconds")
        ax.set_ylabel("texture RMSE" if rows.get("texture") else "max |p - truth|")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.pareto", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--jobs", default=",".join(JOBS))
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--budgets", default="0.5,1,2,4", help="multiples of each example's iterations")
    parser.add_argument("--loop-views", default="1,2,all")
    parser.add_argument("--variant", choices=sorted(VARIANTS) + [OTHER], default=None,
                        help="a bench.regime variant run beside the default at the default's seconds; 'other': "
                             "the method of prb and ndrf-lhs that auto did not choose, per budget")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "pareto.json")
    parser.add_argument("--reuse-default", action="store_true",
                        help="keep the default job's runs already in --out for the same budgets and seeds (rerun "
                             "only the loops)")
    parser.add_argument("--report-only", action="store_true",
                        help="run nothing: write --out's table and plot again from its results")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    seeds = [int(v) for v in args.seeds.split(",")]
    budgets = [float(v) for v in args.budgets.split(",")]
    views = [] if args.loop_views == "none" else [None if v.strip() == "all" else int(v)
                                                  for v in args.loop_views.split(",")]
    results: dict = json.loads(args.out.read_text())["results"] if args.out.exists() else {}
    names = [] if args.report_only else [j.strip() for j in args.jobs.split(",") if j.strip()]
    for name in names:
        job = json.loads((ROOT / "examples" / f"{name}.json").read_text())
        texture = any(p["key"].endswith(".data") for p in job["parameters"])
        rows: dict = {"texture": texture, "default": {}, "loops": {}, "dropped": dropped(job)}
        done = results.get(name, {}).get("default", {}) if args.reuse_default else {}
        for budget in budgets:
            iterations = max(2, int(round(budget * job["iterations"])))
            if len(done.get(str(budget), [])) == len(seeds):      # --reuse-default: measured already
                rows["default"][str(budget)] = done[str(budget)]
                continue
            rows["default"][str(budget)] = []
            for seed in seeds:
                run = run_default(job, seed, iterations)
                log.info("%s budget %s seed %d: %d iterations, %.1f s, error %.4g (last iterate %s)", name, budget,
                         seed, run["iterations"], run["seconds"], run["error"], run.get("last_error"))
                rows["default"][str(budget)].append(run)
        seconds = {b: float(np.median([r["seconds"] for r in rows["default"][str(b)]])) for b in budgets}
        for seed in seeds if views else []:
            rows["loops"][str(seed)] = run_loops(job, seed, views, seconds, texture)
        if args.variant:
            rows["variant"] = {"name": args.variant,
                               "runs": run_variant(job, seeds, args.variant, rows["default"], seconds)}
        results[name] = rows
        args.out.write_text(json.dumps({"machine": machine(), "results": results}, indent=1))
    lines, checks = [], {}
    for name, rows in results.items():
        label = name if not rows.get("dropped") else f"{name} (the default recipe: not its {', '.join(rows['dropped'])})"
        table, checks[label] = summarize(label, rows)
        lines += table
    text = markdown_table(["job", "budget (x iterations)", "default: error median (range)", "default s",
                           "best loop: error median (range)", "loop s", "best loop setting", "default <= loop",
                           "variant: error median (range)", "variant s", "default <= variant"], lines)
    text += "\n\n" + markdown_table(
        ["job", "median error by budget", "never worse as the budget grows", "coverage of ±2 SE",
         "median |error| / SE", "scalars"],
        [[name, ", ".join(f"{m:.4f}" for m in c["medians"]), "yes" if c["median_never_worse"] else "no",
          "-" if c["coverage_2se"] is None else f"{c['coverage_2se']:.1%}",
          "-" if c["median_z"] is None else f"{c['median_z']:.2f}", c["scalars"]] for name, c in checks.items()])
    args.out.write_text(json.dumps({"machine": machine(), "results": results, "checks": checks}, indent=1))
    plot(results, args.out.with_suffix(".png"))
    write_markdown(args.out, "bench.pareto", argv, text + f"\n\n![error against seconds]({args.out.stem}.png)")
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

"""Accuracy against time, measured on what a user takes home: the final answer of a run at a
budget, for the default job and for the best Mitsuba tutorial loop given the same time.

``python -m bench.pareto [--jobs demo,room-open-8,room-closed-8,hidden-object,textured-box]
[--seeds 0,1,2] [--budgets 0.5,1,2,4] [--loop-views 1,2,all] [--out bench/results/pareto.json]
[--reuse-default]``

For each job of ``examples/`` (reduced to its scene, parameters, targets and iterations: what a
user sets) and each budget ``m``, the default job runs ``m x`` the example's iterations, once per
seed (its targets rendered from that seed), through ``run_local`` (the product's loop, records
and files included). Its answer is ``summary.json``'s ``final`` (the estimate), its time the
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
from bench.regime import default_job

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
JOBS = ("demo", "room-open-8", "room-closed-8", "hidden-object", "textured-box")


def error_of(values, truth, texture: bool) -> float:
    difference = np.asarray(values, np.float64) - np.asarray(truth, np.float64)
    return float(np.sqrt(np.mean(difference ** 2)) if texture else np.max(np.abs(difference)))


def run_default(job: dict, seed: int, iterations: int) -> dict:
    """The default job with ``iterations`` and ``seed``: its answer, standard errors and seconds."""
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    gc.collect()
    events: list[tuple[float, dict]] = []
    spec = JobSpec.model_validate({**default_job(job), "iterations": iterations, "seed": seed})
    with tempfile.TemporaryDirectory() as tmp:
        def on_event(event: dict) -> None:
            if event.get("type") in ("plan", "iteration"):
                events.append((time.perf_counter(), event))

        summary = run_local(spec, Path(tmp) / "job", on_event=on_event)
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
    out = {"seed": seed, "iterations": summary["iterations"], "seconds": seconds, "status": summary["status"],
           "stopped": (summary.get("stopped") or {}).get("reason"), "estimate": summary.get("estimate")}
    if texture is not None:
        out["error"] = error_of(texture["final"], texture["target"], True)
        if texture["last"] is not None:
            out["last_error"] = error_of(texture["last"], texture["target"], True)
        if texture["se"] is not None:
            out["z"] = (np.abs(texture["final"] - texture["target"]) / np.maximum(texture["se"], 1e-12)).ravel().tolist()
    else:
        out["error"] = error_of(summary["final"], summary["target"], False)
        out["last_error"] = error_of(summary["last_iterate"], summary["target"], False)
        if summary.get("standard_error"):
            se = np.asarray(summary["standard_error"])
            out["z"] = (np.abs(np.asarray(summary["final"]) - summary["target"]) / np.maximum(se, 1e-12)).tolist()
            out["standard_error"] = se.tolist()
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
    for budget in budgets:
        runs = rows["default"][budget]
        errors = [r["error"] for r in runs]
        seconds = [r["seconds"] for r in runs]
        loops = {label: [rows["loops"][str(seed)][label][budget] for seed in rows["loops"]]
                 for label in next(iter(rows["loops"].values()))}
        best_label = min(loops, key=lambda label: np.median([r["error"] for r in loops[label]]))
        best = loops[best_label]
        loop_errors, loop_seconds = [r["error"] for r in best], [r["seconds"] for r in best]
        table.append([name, budget, f"{np.median(errors):.4f} ({min(errors):.4f}-{max(errors):.4f})",
                      f"{np.median(seconds):.1f}", f"{np.median(loop_errors):.4f} ({min(loop_errors):.4f}-"
                      f"{max(loop_errors):.4f})", f"{np.median(loop_seconds):.1f}", best_label[5:],
                      "yes" if np.median(errors) <= np.median(loop_errors) else "no"])
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
        for label, color in (("default job", "C0"),):
            xs = [np.median([r["seconds"] for r in rows["default"][b]]) for b in budgets]
            ys = [np.median([r["error"] for r in rows["default"][b]]) for b in budgets]
            lo = [min(r["error"] for r in rows["default"][b]) for b in budgets]
            hi = [max(r["error"] for r in rows["default"][b]) for b in budgets]
            ax.errorbar(xs, ys, yerr=[np.subtract(ys, lo), np.subtract(hi, ys)], marker="o", color=color, label=label,
                        capsize=3)
        labels = list(next(iter(rows["loops"].values())))
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
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "pareto.json")
    parser.add_argument("--reuse-default", action="store_true",
                        help="keep the default job's runs already in --out for the same budgets and seeds (rerun "
                             "only the loops)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    seeds = [int(v) for v in args.seeds.split(",")]
    budgets = [float(v) for v in args.budgets.split(",")]
    views = [None if v.strip() == "all" else int(v) for v in args.loop_views.split(",")]
    results: dict = json.loads(args.out.read_text())["results"] if args.out.exists() else {}
    for name in [j.strip() for j in args.jobs.split(",") if j.strip()]:
        job = json.loads((ROOT / "examples" / f"{name}.json").read_text())
        texture = any(p["key"].endswith(".data") for p in job["parameters"])
        rows: dict = {"texture": texture, "default": {}, "loops": {}}
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
        for seed in seeds:
            rows["loops"][str(seed)] = run_loops(job, seed, views, seconds, texture)
        results[name] = rows
        args.out.write_text(json.dumps({"machine": machine(), "results": results}, indent=1))
    lines, checks = [], {}
    for name, rows in results.items():
        table, checks[name] = summarize(name, rows)
        lines += table
    text = markdown_table(["job", "budget (x iterations)", "default: error median (range)", "default s",
                           "best loop: error median (range)", "loop s", "best loop setting", "default <= loop"], lines)
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

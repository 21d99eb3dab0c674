"""Where each method wins: whole jobs in the regime the paper claims for NDRF (issue 11).

``python -m bench.regime [--iterations N] [--variants a,b] [--out bench/results/regime.json]``
``python -m bench.regime --check-loss``: how well each end point fits the target (see :func:`check_loss`)
``python -m bench.regime --plot A.json B.json --out F.png``: error against seconds, a panel per file

The job (``examples/bright-room.json``): the closed ``hidden-object`` room with its walls at
albedo 0.95 to recover (from 0.5) together with the hidden sphere's albedo, so light paths are
long: the synthetic target has every bounce (its depth is the measured converged depth), as a
photograph has them. Each variant is the same job through the product's own loop
(:func:`services.jobs.local.run_local`), one after the other in one process, so the ratios hold.
Reported per variant: seconds per iteration (median, after the first), the time at which the
largest parameter error first falls below ``--target-error`` (training warm-up included, target
rendering and depth probing excluded: they are the same for every variant), and the final error.

Variants:

``prb``                 prb at the converged depth, Adam (0.8, 0.99) (the job's defaults)
``prb-beta2-0.9``       the same with Adam (0.8, 0.9): a shorter second-moment memory
``prb-depth-12``        prb truncated at depth 12 against the all-bounce target (what a user who
                        calls Mitsuba's tutorial loop with its default depth gets)
``prb-spp-64``          prb with 64 spp for the candidate and the adjoint pass (16x the samples)
``prb-constant-lr-400``  prb with a constant learning rate for 400 iterations (no decay)
``prb-gauss-newton``    prb, Gauss-Newton steps (``"optimizer": "gauss-newton"``): the Jacobian from
                        one forward-mode render per scalar and iteration
``prb-gauss-newton-spp-16``  the same with 16 spp for the Jacobian and the adjoint pass (4x): is a
                        less noisy forward-mode Jacobian enough for prb?
``ndrf-lhs-gauss-newton``  NDRF, Gauss-Newton steps: the Jacobian from ``dL_theta`` at the camera hits
``*-gauss-newton-cross``  the same with ``"hessian": "cross"``: the curvature from two independent
                        half-sample Jacobians, without the upward bias of their noise
``*-gauss-newton-constant``  the same with a constant trust region (learning rate 0.05, no decay)
``ndrf-lhs-gauss-newton-160``  NDRF, Gauss-Newton, 160 iterations (the decay spread over twice as many)
``ndrf-lhs``            NDRF, camera-hit query, the path-traced candidate at the converged depth
``ndrf-lhs-field``      NDRF with the field candidate on cached first hits (no path tracing per
                        iteration: its cost does not depend on the path length)
``ndrf-lhs-field-gauss-newton``  the same with Gauss-Newton steps
``ndrf-lhs-field-steps-4``  the field candidate with half the training: 100 warm-up steps, 4 per iteration
``ndrf-lhs-field-steps-4-gauss-newton``  the same with Gauss-Newton steps
``ndrf-lhs-field-steps-2[-gauss-newton]``  a quarter of the training: 50 warm-up steps, 2 per iteration
``ndrf-lhs-field-steps-4-live``  half the training, the fields queried without weight averaging
``ndrf-lhs-path-steps-4``, ``-steps-2``  the path-traced candidate, dL_theta at cached camera hits,
                        half / a quarter of the training
``ndrf-lhs-path-adaptive-50[-camera-0.5]``  the same with adaptive steps (at most 50 warm-up, 1 to 8
                        per iteration; with half the residual points where the cameras look)
``ndrf-rhs-adaptive-50``  ndrf-rhs (fresh one-bounce query) with those adaptive steps
``prb-spp-N``           prb with N (1, 4, 16) spp for the candidate and the adjoint pass

``--job examples/room-closed-8.json`` (or ``room-open-8.json``) runs the variants on the multi-view
rooms instead: 8 views of 128x128, 6 scalars, 120 iterations, 1 spp by default.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import chosen, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
JOB = ROOT / "examples" / "bright-room.json"

#: the candidate from L_phi at cached first hits (no path tracing per iteration)
FIELD = {"candidate": "field", "first_hits": "cached"}

#: the path-traced candidate, with ndrf-lhs querying dL_theta at camera hits cached once per job
CACHED = {"first_hits": "cached"}

#: half and a quarter of the rooms' training (200 warm-up steps, 8 per iteration)
HALF = {"warmup_steps": 100, "steps_per_iteration": 4}
QUARTER = {"warmup_steps": 50, "steps_per_iteration": 2}

#: short training that the residual norms cut shorter (services/solver/estimators/schedule.py)
ADAPTIVE_50 = {"adaptive_steps": True, "warmup_steps": 50, "min_warmup_steps": 30, "steps_per_iteration": 8,
               "min_steps_per_iteration": 1}

#: name -> changes to the job file
VARIANTS: dict[str, dict] = {
    "prb": {"method": "prb"},
    "prb-beta2-0.9": {"method": "prb", "adam_betas": [0.8, 0.9]},
    "prb-depth-12": {"method": "prb", "render": {"max_depth": 12}},
    "prb-spp-64": {"method": "prb", "render": {"spp": 64, "gradient_spp": 64}},
    "prb-constant-lr-400": {"method": "prb", "final_learning_rate_ratio": 1.0, "iterations": 400},
    "prb-gauss-newton": {"method": "prb", "optimizer": "gauss-newton"},
    "prb-gauss-newton-spp-16": {"method": "prb", "optimizer": "gauss-newton", "render": {"gradient_spp": 16}},
    "ndrf-lhs-gauss-newton": {"method": "ndrf-lhs", "optimizer": "gauss-newton"},
    "prb-gauss-newton-cross": {"method": "prb", "optimizer": "gauss-newton", "hessian": "cross"},
    "ndrf-lhs-gauss-newton-cross": {"method": "ndrf-lhs", "optimizer": "gauss-newton", "hessian": "cross"},
    "ndrf-lhs-gauss-newton-constant": {"method": "ndrf-lhs", "optimizer": "gauss-newton",
                                       "final_learning_rate_ratio": 1.0},
    "prb-gauss-newton-constant": {"method": "prb", "optimizer": "gauss-newton", "final_learning_rate_ratio": 1.0},
    "ndrf-lhs-gauss-newton-160": {"method": "ndrf-lhs", "optimizer": "gauss-newton", "iterations": 160},
    "ndrf-lhs": {"method": "ndrf-lhs"},
    "ndrf-lhs-field": {"method": "ndrf-lhs", "render": FIELD},
    "ndrf-lhs-field-gauss-newton": {"method": "ndrf-lhs", "optimizer": "gauss-newton", "render": FIELD},
    "ndrf-lhs-field-steps-4": {"method": "ndrf-lhs", "render": FIELD,
                               "training": HALF},
    "ndrf-lhs-field-steps-4-live": {"method": "ndrf-lhs", "render": FIELD,
                                    "training": {**HALF, "weight_averaging": None}},
    "ndrf-lhs-path-steps-4": {"method": "ndrf-lhs", "render": CACHED,
                              "training": HALF},
    "ndrf-lhs-path-steps-2": {"method": "ndrf-lhs", "render": CACHED,
                              "training": QUARTER},
    "ndrf-lhs-path-adaptive-50": {"method": "ndrf-lhs", "render": CACHED, "training": ADAPTIVE_50},
    "ndrf-lhs-path-adaptive-50-camera-0.5": {"method": "ndrf-lhs", "render": CACHED,
                                             "training": {**ADAPTIVE_50, "camera_points": 0.5}},
    "ndrf-rhs-adaptive-50": {"method": "ndrf-rhs", "training": ADAPTIVE_50},
    "ndrf-lhs-field-steps-4-gauss-newton": {"method": "ndrf-lhs", "optimizer": "gauss-newton", "render": FIELD,
                                            "training": HALF},
    "ndrf-lhs-field-steps-2": {"method": "ndrf-lhs", "render": FIELD,
                               "training": QUARTER},
    "ndrf-lhs-field-steps-2-gauss-newton": {"method": "ndrf-lhs", "optimizer": "gauss-newton", "render": FIELD,
                                            "training": QUARTER},
    "prb-spp-1": {"method": "prb", "render": {"spp": 1, "gradient_spp": 1}},
    "prb-spp-4": {"method": "prb", "render": {"spp": 4, "gradient_spp": 4}},
    "prb-spp-16": {"method": "prb", "render": {"spp": 16, "gradient_spp": 16}},
}


def _merge(base: dict, change: dict) -> dict:
    out = dict(base)
    for key, value in change.items():
        out[key] = _merge(base.get(key, {}), value) if isinstance(value, dict) else value
    return out


def run_variant(job: dict, target_error: float, budget: float | None = None) -> dict:
    """One whole job; with ``budget``, stopped (as a cancel: with its records) after that many
    seconds of wall clock, for variants too slow to run to the end of the job's schedule."""
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.store.job import JobFiles
    from services.store.local import FolderStore

    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()

        def over_budget() -> str | None:
            return "canceled" if budget is not None and time.perf_counter() - started > budget else None

        summary = run_local(JobSpec.model_validate(job), Path(tmp) / "job", should_stop=over_budget)
        wall = time.perf_counter() - started
        files = JobFiles(FolderStore(tmp), "job")
        records = [files.iteration_record(k) for k in files.iterations()]
        depths = (files.read("plan.json") or {}).get("depths")
    target = np.asarray(summary["target"])
    elapsed, curve = 0.0, []
    for record in records:
        elapsed += sum(record["seconds"].values())
        error = float(np.max(np.abs(np.asarray(record["updated_parameters"]) - target)))
        curve.append({"iteration": record["iteration"], "seconds": elapsed, "error": error,
                      "parameters": record["updated_parameters"]})
    reached = next((c for c in curve if c["error"] < target_error), None)
    per_iteration = [b["seconds"] - a["seconds"] for a, b in zip(curve, curve[1:], strict=False)]
    phases = {name: float(np.median([r["seconds"].get(name, 0.0) for r in records[1:]]))
              for name in (records[-1]["seconds"] if len(records) > 1 else {})}
    return {"phases": phases, "status": summary["status"], "final": summary["final"], "target": summary["target"],
            "wall_seconds": wall, "seconds_per_iteration": float(np.median(per_iteration)) if per_iteration else None,
            "first_iteration_seconds": curve[0]["seconds"] if curve else None,
            "reached": reached, "final_error": curve[-1]["error"] if curve else None, "curve": curve,
            "depths": depths}


def settled(curve: list[dict], target_error: float) -> dict | None:
    """The first point of ``curve`` after which the error stays below ``target_error`` to the end."""
    for i, point in enumerate(curve):
        if all(c["error"] < target_error for c in curve[i:]):
            return point
    return None


def table(results: dict, target_error: float) -> str:
    from bench.common import markdown_table

    rows = []
    for name, r in results.items():
        reached, stays = r["reached"], settled(r["curve"], target_error)
        rows.append([name, f"{r['first_iteration_seconds']:.1f}", f"{r['seconds_per_iteration']:.2f}",
                     f"{reached['iteration']} ({reached['seconds']:.0f} s)" if reached else "not reached",
                     f"{stays['iteration']} ({stays['seconds']:.0f} s)" if stays else "-",
                     f"{r['final_error']:.3f}" + (f" (stopped by --budget after {len(r['curve'])} iterations)"
                                                  if r.get("status") == "canceled" else ""),
                     f"{r['wall_seconds']:.0f}"])
    return markdown_table(["variant", "iteration 0 s (warm-up)", "s / iteration", f"error < {target_error} at",
                           "and stays below from",
                           "final max error", "job wall s"], rows)


def check_loss(path: Path, spp: int = 256) -> str:
    """The image error at the truth and at each variant's end point, from ``spp``-spp renders at
    the target's depth: ``E[(y - t)²] = bias² + Var(y)`` per value, so each point is rendered
    twice with independent seeds and ``Var(y)`` (half the mean squared difference of the two
    renders) is subtracted: what remains is how well the point fits the target."""
    from bench.common import markdown_table
    from schemas.job import JobSpec
    from services.solver.estimators.render import render
    from services.solver.optimize.setup import prepare

    saved = json.loads(path.read_text())
    prepared = prepare(JobSpec.model_validate(saved["job"]))
    params, target = prepared.problem.parameters, prepared.targets[0].astype(np.float64)
    points = [("truth", prepared.target_values)] + [(n, r["final"]) for n, r in saved["results"].items()]
    rows = []
    for name, values in points:
        params.assign(np.asarray(values, np.float64))
        a, b = (render(prepared.problem, spp=spp, seed=seed, max_depth=prepared.depths["target"]).astype(np.float64)
                for seed in (11, 12))
        mse = (np.mean((a - target) ** 2) + np.mean((b - target) ** 2)) / 2
        variance = np.mean((a - b) ** 2) / 2
        rows.append([name, f"{mse:.5f}", f"{variance:.5f}", f"{mse - variance:.5f}"])
    return markdown_table(["end point", f"MSE to the target ({spp} spp)", "Var(y)", "MSE - Var(y)"], rows)


def plot(paths: list[Path], out: Path, target_error: float = 0.02) -> None:
    """Max parameter error against seconds (warm-up included): one panel per job, every variant of
    the result files of that job in it."""
    from bench.report import pyplot, save

    plt = pyplot()
    jobs: dict[str, dict] = {}
    for path in paths:
        saved = json.loads(path.read_text())
        jobs.setdefault(saved["job"].get("name", path.stem), {}).update(saved["results"])
    fig, axes = plt.subplots(1, len(jobs), figsize=(5.6 * len(jobs), 4.4), squeeze=False)
    for ax, (title, results) in zip(axes[0], jobs.items(), strict=True):
        for name, r in results.items():
            ax.plot([c["seconds"] for c in r["curve"]], [c["error"] for c in r["curve"]], label=name,
                    ls="-" if name.startswith("ndrf") else "--")
        ax.axhline(target_error, color="grey", lw=0.8)
        ax.set_yscale("log")
        ax.set_title(title.split(",")[0], fontsize=9)
        ax.set_xlabel("seconds (warm-up and iterations)")
        ax.set_ylabel("max parameter error")
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=7)
    save(fig, out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.regime", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", type=Path, default=JOB, help="the job file (default examples/bright-room.json)")
    parser.add_argument("--iterations", type=int, default=None, help="override the job's iterations")
    parser.add_argument("--variants", default=",".join(VARIANTS), help=f"subset of {', '.join(VARIANTS)}")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--budget", type=float, default=None,
                        help="stop each variant after this many wall-clock seconds (its records so far are kept)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "regime.json")
    parser.add_argument("--plot", type=Path, nargs="+", default=None,
                        help="instead of running: draw error against seconds from these result files into --out (.png)")
    parser.add_argument("--check-loss", action="store_true",
                        help="instead of running: the image error at the truth and at the end points in --out")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    if args.plot:
        plot(args.plot, args.out.with_suffix(".png"), args.target_error)
        return
    if args.check_loss:
        text = check_loss(args.out)
        args.out.with_name(args.out.stem + "-loss.md").write_text(
            f"Command: `python -m bench.regime --check-loss`\n\n{text}\n")
        log.info("\n%s", text)
        return
    base = json.loads(args.job.read_text())
    if args.iterations:
        base["iterations"] = args.iterations
    results = {}
    for name in chosen(args.variants, VARIANTS, parser, "variant"):
        log.info("regime: %s", name)
        results[name] = run_variant(_merge(base, VARIANTS[name]), args.target_error, args.budget)
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps({"job": base, "target_error": args.target_error, "results": results},
                                       indent=1))
    text = table(results, args.target_error)
    write_markdown(args.out, "bench.regime", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

"""What an ``ndrf-lhs`` iteration costs against a ``prb`` iteration, step by step of the changes
that made it cheaper (issue 43), in one process on one job.

``python -m bench.ndrf_cost [--job demo] [--iterations 10] [--repeats 2] [--out bench/results/ndrf_cost.json]``

Rows, each a run of the job through the product's loop (:func:`bench.regime.run_product`: its
clock, its records), the job's other settings as a user gives them, the median seconds per
iteration over ``--iterations`` iterations (the warm-up is outside the median: its 20 steps here,
as in :mod:`bench.gpu_check`, only shorten the run):

1. ``prb``: the default method (the denominator of every ratio);
2. ``ndrf-lhs, as before``: 20 fine-tuning steps per iteration, ``M = 16`` incident samples per
   residual point, and the candidate's gradient and its Jacobian from two camera passes (the base
   class's :meth:`~services.solver.estimators.methods.base.GradientMethod.candidate_gradient_and_images`);
3. ``+ one camera pass``: ``dz/dp`` contracted from the Jacobian's own pass
   (:meth:`~services.solver.estimators.methods.camera_hit.CameraHitMethod.candidate_gradient_and_images`);
4. ``+ 4 steps per iteration``: a warm network after a small parameter step;
5. ``+ M = 4``: four incident samples per residual point (the defaults now).

The rows run in turn ``--repeats`` times (the first pass of each pays Dr.Jit's kernel compilation
and is discarded when ``--repeats`` > 1), and the table gives the median over the kept passes.
The final parameter error after ``--iterations`` iterations is shown beside each row as a
sanity check, not as an accuracy result (that is :mod:`bench.pareto`'s job).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results" / "ndrf_cost.json"
WARMUP = {"warmup_steps": 20}
#: (label, the job's change, whether the camera-hit methods trace one pass for gradient and Jacobian)
ROWS: tuple[tuple[str, dict, bool], ...] = (
    ("prb", {"method": "prb"}, True),
    ("ndrf-lhs, as before", {"method": "ndrf-lhs", "training": {**WARMUP, "steps_per_iteration": 20,
                                                                "incident_samples": 16}}, False),
    ("+ one camera pass", {"method": "ndrf-lhs", "training": {**WARMUP, "steps_per_iteration": 20,
                                                              "incident_samples": 16}}, True),
    ("+ 4 steps per iteration", {"method": "ndrf-lhs", "training": {**WARMUP, "steps_per_iteration": 4,
                                                                    "incident_samples": 16}}, True),
    ("+ M = 4 (the defaults)", {"method": "ndrf-lhs", "training": WARMUP}, True),
)


@contextlib.contextmanager
def camera_passes(one: bool):
    """With ``one`` False, the camera-hit methods trace the gradient's and the Jacobian's rays in
    two passes, as before issue 43 (the base class's method, restored on exit)."""
    from services.solver.estimators.methods.base import GradientMethod
    from services.solver.estimators.methods.camera_hit import CameraHitMethod

    saved = CameraHitMethod.__dict__["candidate_gradient_and_images"]
    if not one:
        CameraHitMethod.candidate_gradient_and_images = GradientMethod.candidate_gradient_and_images  # type: ignore[method-assign]
    try:
        yield
    finally:
        CameraHitMethod.candidate_gradient_and_images = saved  # type: ignore[method-assign]


def measure(job: dict, iterations: int, repeats: int) -> dict:
    from bench.regime import merge, run_product

    passes: dict[str, list[dict]] = {label: [] for label, _, _ in ROWS}
    for repeat in range(repeats):
        for label, change, one in ROWS:
            with camera_passes(one):
                run = run_product(merge(job, change), 0.02, iterations=iterations)
            passes[label].append({"seconds_per_iteration": run["seconds_per_iteration"],
                                  "final_error": run["final_error"], "iterations": run["iterations"]})
            log.info("pass %d %s: %.4f s/iteration", repeat, label, run["seconds_per_iteration"])
    kept = {label: runs[1:] if repeats > 1 else runs for label, runs in passes.items()}
    prb = float(np.median([r["seconds_per_iteration"] for r in kept["prb"]]))
    rows = {}
    for label, runs in kept.items():
        seconds = float(np.median([r["seconds_per_iteration"] for r in runs]))
        rows[label] = {"seconds_per_iteration": seconds, "ratio_to_prb": seconds / prb,
                       "final_error": float(np.median([r["final_error"] for r in runs])), "passes": passes[label]}
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--job", default="demo", help="an example of examples/ (default: demo)")
    parser.add_argument("--iterations", type=int, default=10)
    parser.add_argument("--repeats", type=int, default=2)
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    if args.iterations < 3 or args.repeats < 1:
        parser.error("--iterations must be at least 3 and --repeats at least 1")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")

    job = json.loads((ROOT / "examples" / f"{args.job}.json").read_text())  # as written
    rows = measure(job, args.iterations, args.repeats)
    result = {"machine": machine(), "job": args.job, "iterations": args.iterations, "repeats": args.repeats,
              "rows": rows}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    table = markdown_table(["row", "s / iteration", "x prb", f"error after {args.iterations} iterations"],
                           [[label, r["seconds_per_iteration"], f"{r['ratio_to_prb']:.1f}x", r["final_error"]]
                            for label, r in rows.items()])
    write_markdown(args.out, "bench.ndrf_cost", argv, f"Job `{args.job}`, one process.\n\n{table}")
    log.info("wrote %s\n%s", args.out, table)


if __name__ == "__main__":
    main()

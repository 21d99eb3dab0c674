"""How long a ``prb`` job's first iteration takes, by its size: the throughput behind the cost
estimate at submission (#46, ``services.limits.check_first_iteration``).

    python -m bench.first_iteration [--cases adam-512-4,lm-256-4x4] [--out bench/results/first_iteration.json]

Each case is a ``prb`` job on a built-in scene (the Cornell box of ``examples/demo.json``, one
view; ``room-open-8``'s 8 views for the batches of several views), run in-process through
``run_local`` and stopped after its second iteration; timed: iteration 0's ``gradient`` phase (its
renders: the candidate and adjoint pass under Adam, the candidate and one forward-mode render per
channel group of the Jacobian under Levenberg-Marquardt; kernel compilation included, as a job's
first iteration pays it) and iteration 1's (warm). The cases vary the resolution, the spp, the
views per iteration and the scalars (1 to 4 RGB values of the box: 1 to 4 channel groups, each a
forward-mode render per view). The samples of each case are the count the submission check
computes (:func:`services.limits.first_iteration_samples`: pixels of the first views x
samples per pixel of their renders).

Fit: ``seconds = samples / rate``, the rate the median of the cases' samples per second of the
first iteration, among the cases of at least :data:`FIT_SAMPLES` samples (below, the fixed cost
of an iteration dominates: 0.02 to 0.8 s, kernel compilation mostly); reported with each case's
ratio of measured to modelled seconds, the model's error. On a 2-core AMD EPYC CPU
(``bench/results/first_iteration.md``) the large cases' ratios stay within 0.84 to 1.08 of one
run's median, Adam's and Levenberg-Marquardt's alike (an Adam render, its primal and adjoint
passes, costs about one forward-mode render of the Jacobian); between runs on the shared machine
the rate itself moved by a factor 2 (5.4e5 to 1.2e6 samples per second).
``NDRF_MAX_WORKER_SAMPLES_PER_SECOND`` defaults to the slowest rate rounded down (5e5), so the
estimate errs towards long; the check refuses only past half the budget.
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

log = logging.getLogger("bench.first_iteration")
ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results" / "first_iteration.json"
#: Cases below this many samples are reported but left out of the fit.
FIT_SAMPLES = 1 << 20

#: The Cornell box's RGB scalars, with their target values (the light's within [0, 1] too: a dimmer light).
VALUES = {"red.reflectance.value": [0.57, 0.04, 0.04], "green.reflectance.value": [0.1, 0.45, 0.08],
          "white.reflectance.value": [0.7, 0.7, 0.7], "light.emitter.radiance.value": [0.9, 0.7, 0.35]}


def _job(scene: str, size: int, spp: int, optimizer: str, walls: int, views: int) -> dict:
    if scene == "room-open-8":
        keys = {"walls.reflectance.value": [0.85] * 3, "ball.reflectance.value": [0.8, 0.2, 0.1]}
    else:
        keys = dict(list(VALUES.items())[:walls])
    return {"name": "first iteration", "scene": {"builtin": scene}, "method": "prb", "optimizer": optimizer,
            "parameters": [{"key": k, "init": [0.4, 0.4, 0.4], "bounds": [0.0, 1.0]} for k in keys],
            "targets": {"synthetic": {"values": keys, "spp": 4}}, "iterations": 50, "views_per_iteration": views,
            "render": {"resolution": [size, size], "spp": spp, "gradient_spp": spp}, "seed": 0}


#: name -> (scene, resolution, spp, optimizer, RGB parameters, views per iteration)
CASES = {
    "adam-64-1": ("cornell-box", 64, 1, "adam", 1, 1),
    "adam-256-4": ("cornell-box", 256, 4, "adam", 1, 1),
    "adam-512-4": ("cornell-box", 512, 4, "adam", 1, 1),
    "adam-256-32": ("cornell-box", 256, 32, "adam", 1, 1),
    "adam-views8-128-8": ("room-open-8", 128, 8, "adam", 2, 8),
    "lm-256-4x1": ("cornell-box", 256, 4, "levenberg-marquardt", 1, 1),
    "lm-256-4x4": ("cornell-box", 256, 4, "levenberg-marquardt", 4, 1),
    "lm-512-4x2": ("cornell-box", 512, 4, "levenberg-marquardt", 2, 1),
}


def measure(name: str) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.limits import first_iteration_samples

    scene, size, spp, optimizer, walls, views = CASES[name]
    spec = JobSpec.model_validate(_job(scene, size, spp, optimizer, walls, views))
    sensors = [[size, size]] * (8 if scene == "room-open-8" else 1)
    pixels, per_pixel, groups = first_iteration_samples(spec, sensors, 3 * len(spec.parameters), every_view=False)
    records: list[dict] = []
    with tempfile.TemporaryDirectory() as tmp:
        started = time.perf_counter()
        summary = run_local(spec, Path(tmp) / "job", on_event=lambda e: records.append(e)
                            if e.get("type") == "iteration" else None,
                            should_stop=lambda: "canceled" if len(records) >= 2 else None)
        total = time.perf_counter() - started
    if len(records) < 2:
        raise RuntimeError(f"{name}: {summary.get('status')} {summary.get('error')}")
    first, warm = records[0]["seconds"]["gradient"], records[1]["seconds"]["gradient"]
    samples = pixels * per_pixel
    return {"case": name, "scene": scene, "resolution": size, "spp": spp, "optimizer": optimizer,
            "scalars": 3 * len(spec.parameters), "views": views, "jacobian_renders": groups, "samples": samples,
            "first_seconds": first, "warm_seconds": warm, "run_seconds": total,
            "samples_per_second": samples / first}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.first_iteration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--cases", default=",".join(CASES), help="comma-separated, of " + ", ".join(CASES))
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    rows = []
    for name in chosen(args.cases, CASES, parser, "case"):
        rows.append(measure(name))
        log.info("%s", rows[-1])
    fitted = [r["samples_per_second"] for r in rows if r["samples"] >= FIT_SAMPLES] or \
        [r["samples_per_second"] for r in rows]
    rate, slowest = float(np.median(fitted)), float(min(fitted))
    for r in rows:
        r["measured_over_model"] = r["first_seconds"] / (r["samples"] / rate)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"machine": machine(), "rows": rows, "rate_median": rate,
                                    "rate_slowest": slowest}, indent=1))
    table = markdown_table(
        ["case", "resolution", "spp", "optimizer", "scalars", "views", "Jacobian renders", "samples",
         "iteration 0 s", "iteration 1 s", "samples / s", "measured / model"],
        [[r["case"], r["resolution"], r["spp"], r["optimizer"], r["scalars"], r["views"], r["jacobian_renders"],
          r["samples"], r["first_seconds"], r["warm_seconds"], r["samples_per_second"], r["measured_over_model"]]
         for r in rows])
    text = (f"The ``gradient`` phase of a ``prb`` job's first two iterations, in-process.\n\n{table}\n\n"
            f"Fit, cases of at least {FIT_SAMPLES} samples: seconds = samples / {rate:.3g} (the median rate); "
            f"the slowest case traced {slowest:.3g} samples per second.")
    write_markdown(args.out, "bench.first_iteration", argv, text)
    log.info("wrote %s\n%s", args.out, text)


if __name__ == "__main__":
    main()

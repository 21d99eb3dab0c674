"""Samples per pixel of ``ndrf gradient``'s images: their error against ``prb`` and their seconds.

``python -m bench.investigations.gradient_spp [--job hidden-object] [--method ndrf-rhs] [--spps 1,4,16,64] [--seeds 0,1]``

The command's own path (:func:`services.solver.optimize.evaluate.evaluate_gradient`: ``prepare``,
``make_method``, ``trainer_for``, the job's warm-up training, ``method.images``), trained once per
seed of the job, then queried at each spp; the reference is the mean of two independent draws of
``prb``'s images at ``--reference-spp`` with the job's path depth (its own relative noise, half
the two draws' distance, is the floor of every error below). Reported per spp: the relative L2
error ``||g - g_ref|| / ||g_ref||`` over all scalars, pixels and channels (mean over the seeds and
each one), and the query's seconds (median; the training is the same for every spp). The
``ndrf gradient`` default (``cli.gradient.GRADIENT_SPP``) rests on this table: the inverse loop's
1-spp ``render.gradient_spp`` serves an optimizer that averages noise across iterations, not one
image a user looks at.
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, relative_error, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]


def images_of(prepared, method, fields, spp: int, seed: int) -> np.ndarray:
    """``(S·P, H, W, 3)``: every sensor's gradient images, stacked."""
    from services.solver.seeds import derive_seed

    return np.concatenate([method.gradient_images(prepared.problem, fields, spp=spp, seed=derive_seed(seed, "gradient", s),
                                         sensor=s) for s in sorted(prepared.targets)])


def run(job: dict, method_name: str, spps: list[int], seeds: list[int], reference_spp: int) -> dict:
    from schemas.job import JobSpec
    from services.solver.estimators.methods import Fields, make_method
    from services.solver.optimize.setup import prepare
    from services.solver.training.trainer import fields_of, trainer_for

    out: dict = {"spp": {str(spp): {"errors": [], "seconds": []} for spp in spps}, "training_seconds": []}
    for seed in seeds:
        spec = JobSpec.model_validate({**job, "seed": seed})
        prepared = prepare(spec, method=method_name)
        if seed == seeds[0]:
            prb = make_method("prb", None, prepared.depth)
            t = time.perf_counter()
            halves = [images_of(prepared, prb, Fields(), reference_spp, 1000 + k) for k in range(2)]
            out["reference_seconds"] = time.perf_counter() - t
            reference = (halves[0] + halves[1]) / 2
            # the mean of two independent halves: its error is half their distance (in expectation)
            out["reference_noise"] = relative_error(halves[0], halves[1]) / 2
            log.info("reference: %.1f s, noise %.3f", out["reference_seconds"], out["reference_noise"])
        method = make_method(method_name, prepared.problem.effects, prepared.depth)
        t = time.perf_counter()
        trainer = trainer_for(prepared.problem, method, spec.training, spec.seed)
        if trainer is not None:
            trainer.train(spec.training.warmup_steps)
        out["training_seconds"].append(time.perf_counter() - t)
        fields = fields_of(trainer)
        images_of(prepared, method, fields, spps[0], seed)          # kernels compiled outside the clock
        for spp in spps:
            t = time.perf_counter()
            images = images_of(prepared, method, fields, spp, seed)
            row = out["spp"][str(spp)]
            row["seconds"].append(time.perf_counter() - t)
            row["errors"].append(relative_error(images, reference))
            log.info("seed %d spp %d: error %.3f, %.2f s", seed, spp, row["errors"][-1], row["seconds"][-1])
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.gradient_spp", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", default="hidden-object", help="a job file of examples/ (its name)")
    parser.add_argument("--method", default="ndrf-rhs")
    parser.add_argument("--spps", default="1,4,16,64")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--reference-spp", type=int, default=2048, help="spp of each of the two prb draws")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    from services.solver.backend import use_mitsuba, use_torch

    use_torch(), use_mitsuba()
    job = json.loads((ROOT / "examples" / f"{args.job}.json").read_text())
    spps, seeds = [int(v) for v in args.spps.split(",")], [int(v) for v in args.seeds.split(",")]
    result = run(job, args.method, spps, seeds, args.reference_spp)
    out = args.out or ROOT / "bench" / "results" / f"gradient_spp-{args.job}.json"
    out.write_text(json.dumps({"machine": machine(), "job": args.job, "method": args.method, "seeds": seeds,
                               "reference_spp": args.reference_spp, **result}, indent=1))
    rows = []
    for spp in spps:
        row = result["spp"][str(spp)]
        rows.append([spp, f"{np.mean(row['errors']):.3f}", ", ".join(f"{e:.3f}" for e in row["errors"]),
                     f"{np.median(row['seconds']):.2f}"])
    text = (f"`{args.method}` on `{args.job}` ({job['render'].get('resolution')}, "
            f"{job['training']['warmup_steps']} warm-up steps, {np.mean(result['training_seconds']):.0f} s of "
            f"training per seed) against `prb` at 2 x {args.reference_spp} spp (its own noise: "
            f"{result['reference_noise']:.3f}).\n\n"
            + markdown_table(["spp", "relative error (mean)", f"per seed {args.seeds}", "query s (median)"], rows))
    write_markdown(out, "bench.investigations.gradient_spp", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

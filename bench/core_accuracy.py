"""Gradient accuracy of every method against prb, with the training time it took.

    python -m bench.core_accuracy [--budget SECONDS] [--scene cornell-box] [--key red.reflectance.value]

Relative L2 error ||g - g_ref|| / ||g_ref|| of the gradient images (64x64, all scalars of the key)
against prb at 4096 spp (max depth 12, no Russian roulette), on all pixels and on the pixels the
parameter's own BSDF never touches (indirect gradients only). The fields train for a wall-clock
budget; each method's row reports the training time it needed (0 for direct and prb). Writes
bench/results/core_accuracy-<scene>.md.
"""

from __future__ import annotations

import argparse
import logging
import platform
import time
from pathlib import Path

import numpy as np

from services.solver.estimators.render import PathDepth


def relative(g, ref, where=None):
    if where is not None:
        g, ref = g[:, where], ref[:, where]
    return float(np.linalg.norm(g - ref) / np.linalg.norm(ref))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="cornell-box")
    parser.add_argument("--key", default="red.reflectance.value")
    parser.add_argument("--budget", type=float, default=170.0, help="training seconds")
    parser.add_argument("--reference-spp", type=int, default=4096)
    parser.add_argument("--query-spp", type=int, default=16)
    parser.add_argument("--seed", type=int, default=0, help="seed of the fields' initialisation and training samples")
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    from schemas.solver import TrainingConfig
    from services.solver.backend import use_mitsuba, use_torch
    use_mitsuba(), use_torch()
    from services.solver.estimators.methods import Fields, make_method
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.training.trainer import FieldTrainer

    scene = load_scene(builtin=args.scene, resolution=(64, 64))
    problem = Problem(scene, ParameterSet(scene.params, [args.key]))
    t = time.perf_counter()
    reference = make_method("prb", None, PathDepth(12, None)).gradient_images(
        problem, Fields(), spp=args.reference_spp, seed=12345)
    reference_seconds = time.perf_counter() - t

    trainer = FieldTrainer(problem, TrainingConfig(), radiance=True, differential=True, seed=args.seed)
    t = time.perf_counter()
    while time.perf_counter() - t < args.budget:
        trainer.step()
    trained = time.perf_counter() - t
    fields = trainer.queried()

    rows = []
    direct = None
    live = Fields(trainer.radiance, trainer.differential)  # the last iterate, without weight averaging
    queries = [("ndrf-lhs", "ndrf-lhs", fields), ("ndrf-lhs, live weights", "ndrf-lhs", live),
               ("ndrf-rhs", "ndrf-rhs", fields), ("radiance-cache", "radiance-cache", fields),
               ("direct", "direct", Fields()), ("prb", "prb", Fields())]
    for name, method_name, used in queries:
        method = make_method(method_name)
        t = time.perf_counter()
        images = method.gradient_images(problem, used, spp=args.query_spp, seed=1)
        query = time.perf_counter() - t
        if name == "direct":
            direct = images
        rows.append((name, images, query, 0.0 if name in ("direct", "prb") else trained))
    off = np.abs(direct).sum(axis=(0, 3)) == 0
    lines = [
        f"# Gradient accuracy on `{args.scene}` / `{args.key}` (64x64)",
        "",
        f"Reference: prb, {args.reference_spp} spp, depth 12, no Russian roulette ({reference_seconds:.0f} s). "
        f"Query: {args.query_spp} spp. Fields: default TrainingConfig, {trainer.steps} steps, queried through "
        f"their weight averages (β = {trainer.config.weight_averaging}) except where the row says live weights.",
        f"Machine: {platform.processor() or platform.machine()}, {__import__('os').cpu_count()} cores. "
        f"Command: `python -m bench.core_accuracy --scene {args.scene} --key {args.key} --budget {args.budget:g}"
        f"{f' --seed {args.seed}' if args.seed else ''}`",
        "",
        "| method | rel. L2 error | error off the parameter's surface | training s | query s |",
        "|---|---|---|---|---|",
    ]
    for name, images, query, train_s in rows:
        off_err = relative(images, reference, off) if off.any() and np.linalg.norm(reference[:, off]) > 0 else float("nan")
        lines.append(f"| {name} | {relative(images, reference):.4f} | {off_err:.4f} | {train_s:.0f} | {query:.2f} |")
    text = "\n".join(lines) + "\n"
    logging.getLogger("bench.core_accuracy").info("\n%s", text)
    out = Path(__file__).parent / "results" / f"core_accuracy-{args.scene}{f'-seed{args.seed}' if args.seed else ''}.md"
    out.write_text(text)


if __name__ == "__main__":
    main()

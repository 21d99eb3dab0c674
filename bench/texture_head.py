"""The many-parameter head (``training.head``, paper Sec. 8) on a texture that acts through
interreflection: the built-in ``textured-floor`` (a 16 x 16 albedo, 768 scalars, on a floor that
its 2 cameras of 32 x 32 never see; they see the walls it lights).

``python -m bench.texture_head gradient [--ref-spp 4096] [--steps 400] [--rank 16] [--points 4096] [--incident 16]``
``python -m bench.texture_head race [--seconds 600] [--rank 16]``

``gradient``: at the initial texture (0.5 grey), ``dz/dp`` of the l2 loss against the targets
(rendered at ``--target-spp``), ``dz/dy = 2 (y - target) / size`` from a candidate at 256 spp, summed
over both views. The reference is ``prb`` at ``--ref-spp``; a second ``prb`` run at the same spp
with another seed gives the reference's own noise (their difference is sqrt(2) times it). Compared:
``ndrf-rhs`` with the head after ``--steps`` training steps (``--spp`` camera rays per pixel), the
same with the head's coefficients zeroed (the exact local terms alone: what the head adds), and
``prb`` at the spp whose time matches the head's query. Relative error: ``||g - g_ref|| / ||g_ref||``.

``race``: the same job recovered by ``prb`` and by ``ndrf-rhs`` with the head (Adam at ``--lr``,
both views per iteration at ``--race-spp``, optionally ``--smoothness``, the texture written every
``--every`` iterations; the head: ``--steps`` warm-up steps, ``--fine-tune`` steps per iteration,
``--points`` x ``--incident`` samples per step), each for ``--seconds`` of wall time at most (from
the plan event: target rendering excluded); reported: the texture PSNR against the true texture
(:func:`~services.solver.scene.textured.smooth_albedo`, peak 1) over time, the time to 30 dB and to
``--psnr`` dB (or "never"), and the image loss of the last 20 iterations next to the loss at the
true texture (``init`` null, ``--floor-iterations`` iterations at learning rate 1e-9). A run whose
loss is at that floor fits the photographs as well as the truth: a higher PSNR is then beyond what
the photographs tell, whatever the method.

Both ran on a shared 2-core machine (other jobs beside them): seconds vary with its load.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
SCENE = "textured-floor"
KEY = "floor-paint.reflectance.data"


def job(method: str, rank: int, iterations: int = 1, target_spp: int = 1024, learning_rate: float = 0.03,
        spp: int = 16, **extra) -> dict:
    out = {"scene": {"builtin": SCENE}, "parameters": [{"key": KEY, "init": 0.5}],
           "targets": {"synthetic": {"values": {KEY: None}, "spp": target_spp}}, "iterations": iterations,
           "method": method, "optimizer": "adam", "learning_rate": learning_rate, "views_per_iteration": 2,
           "render": {"spp": spp, "gradient_spp": spp}}
    if method == "ndrf-rhs":
        out["training"] = {"head": {"rank": rank}}
    out.update(extra)
    return out


def relative(g: np.ndarray, ref: np.ndarray) -> float:
    return float(np.linalg.norm(g - ref) / np.linalg.norm(ref))


def gradient(args) -> dict:
    from schemas.job import JobSpec
    from services.solver.estimators.methods.prb import Prb
    from services.solver.estimators.render import render
    from services.solver.optimize.build import build
    from services.solver.optimize.resolve import resolve
    from services.solver.optimize.setup import prepare

    spec = JobSpec.model_validate(job("ndrf-rhs", args.rank, target_spp=args.target_spp,
                                      training={"head": {"rank": args.rank}, "warmup_steps": args.steps,
                                                "residual_points": args.points, "incident_samples": args.incident}))
    prepared, measures = prepare(spec)
    problem = prepared.problem
    recipe = resolve(spec, problem.parameters, len(prepared.targets), measures)
    built = build(prepared, recipe)
    assert built.trainer is not None
    started = time.perf_counter()
    built.trainer.train(args.steps)
    train_seconds = time.perf_counter() - started
    fields = built.trainer.queried()
    zeroed = copy.deepcopy(fields.head)
    zeroed.coefficients.data.zero_()
    exact_only = type(fields)(fields.radiance, head=zeroed)
    prb = Prb(depth=recipe.depth)
    sensors = sorted(prepared.targets)
    dz_dy = {}
    for s in sensors:
        y = render(problem, spp=256, seed=1000 + s, sensor=s, depth=recipe.depth)
        dz_dy[s] = (2.0 * (y - prepared.targets[s]) / y.size).astype(np.float32)

    def total(method, f, spp, seed):
        begin = time.perf_counter()
        g = sum(method.loss_gradient(problem, f, dz_dy[s], spp=spp, seed=seed + s, sensor=s) for s in sensors)
        return np.asarray(g), time.perf_counter() - begin

    ref, ref_seconds = total(prb, None, args.ref_spp, 11)
    ref2, _ = total(prb, None, args.ref_spp, 23)
    head, head_seconds = total(built.method, fields, args.spp, 5)
    local, _ = total(built.method, exact_only, args.spp, 5)
    matched_spp = max(1, int(round(args.ref_spp * head_seconds / ref_seconds)))
    cheap, cheap_seconds = total(prb, None, matched_spp, 31)
    rows = [
        {"estimate": f"prb {args.ref_spp} spp, second seed (reference noise x sqrt 2)", "seconds": ref_seconds,
         "relative_error": relative(ref2, ref)},
        {"estimate": f"ndrf-rhs + head, {args.spp} spp", "seconds": head_seconds,
         "relative_error": relative(head, ref)},
        {"estimate": f"ndrf-rhs + head, coefficients zeroed (exact local terms only), {args.spp} spp",
         "seconds": head_seconds, "relative_error": relative(local, ref)},
        {"estimate": f"prb {matched_spp} spp (the head's query time)", "seconds": cheap_seconds,
         "relative_error": relative(cheap, ref)},
    ]
    indirect = float(np.linalg.norm(head - local) / np.linalg.norm(head))
    log.info("head: relative error %.3f; train %.1f s", rows[1]["relative_error"], train_seconds)
    return {"rows": rows, "train_seconds": train_seconds, "steps": args.steps, "rank": args.rank,
            "ref_spp": args.ref_spp, "spp": args.spp, "scalars": int(problem.parameters.n),
            "head_share_of_gradient": indirect,
            "cosine": float(head @ ref / (np.linalg.norm(head) * np.linalg.norm(ref)))}


def race_one(method: str, args) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.solver.scene.textured import smooth_albedo

    truth = smooth_albedo().astype(np.float64)
    clock: dict[int, float] = {}
    losses: dict[int, float] = {}
    extra = {"images_every": args.every, "checkpoint_every": 100000}
    if args.smoothness != "none":
        extra["textures"] = {"smoothness": args.smoothness, "smoothness_weight": args.weight}
    spec = job(method, args.rank, iterations=args.iterations, target_spp=args.target_spp,
               learning_rate=args.lr, spp=args.race_spp, **extra)
    if method == "ndrf-rhs":
        spec["training"] = {"head": {"rank": args.rank}, "warmup_steps": args.steps,
                            "steps_per_iteration": args.fine_tune, "residual_points": args.points,
                            "incident_samples": args.incident}
    with tempfile.TemporaryDirectory() as tmp:
        start: list[float] = []

        def on_event(event: dict) -> None:
            if event.get("type") == "plan" and not start:
                start.append(time.perf_counter())
            elif event.get("type") == "iteration":
                k = int(event["iteration"])
                clock[k] = time.perf_counter() - start[0]
                if event.get("loss") is not None:
                    losses[k] = float(event["loss"])
                if clock[k] > args.seconds:
                    raise TimeoutError("out of time")

        with contextlib.suppress(TimeoutError):   # the time limit ends the run
            run_local(JobSpec.model_validate(spec), Path(tmp) / "job", on_event=on_event)
        folder = Path(tmp) / "job"
        curve = []
        for k in sorted(clock):
            written = folder / "iterations" / f"{k:06d}" / "textures" / f"{KEY}.npy"
            if written.exists():
                mse = float(np.mean((np.load(written).astype(np.float64) - truth) ** 2))
                curve.append({"iteration": k, "seconds": clock[k], "psnr": 10.0 * float(np.log10(1.0 / mse))})
    reached = {f"{threshold:g}": next((c for c in curve if c["psnr"] >= threshold), None)
               for threshold in (30.0, args.psnr)}
    best = max(curve, key=lambda c: c["psnr"]) if curve else None
    last = [losses[k] for k in sorted(losses)[-20:]]
    return {"method": method, "iterations": len(clock), "reached": reached, "best": best, "curve": curve,
            "final_loss": float(np.mean(last)) if last else None}


def noise_floor(args) -> float:
    """The image loss at the true texture (``init`` null: the scene's own texture, which is also
    the target's): the mean over ``--floor-iterations`` iterations whose steps are too small to
    move it (learning rate 1e-9); the loss no texture can beat on average."""
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    spec = job("prb", args.rank, iterations=args.floor_iterations, target_spp=args.target_spp,
               learning_rate=1e-9, spp=args.race_spp, checkpoint_every=100000)
    spec["parameters"] = [{"key": KEY, "init": None}]
    losses: list[float] = []

    def on_event(event: dict) -> None:
        if event.get("type") == "iteration" and event.get("loss") is not None:
            losses.append(float(event["loss"]))

    with tempfile.TemporaryDirectory() as tmp:
        run_local(JobSpec.model_validate(spec), Path(tmp) / "job", on_event=on_event)
    return float(np.mean(losses))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.texture_head", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("what", choices=["gradient", "race"])
    parser.add_argument("--rank", type=int, default=16)
    parser.add_argument("--steps", type=int, default=400, help="training steps of the head before its gradient")
    parser.add_argument("--spp", type=int, default=64, help="camera rays per pixel of the head's gradient")
    parser.add_argument("--ref-spp", type=int, default=4096)
    parser.add_argument("--target-spp", type=int, default=1024)
    parser.add_argument("--seconds", type=float, default=600.0, help="race: wall-time limit per method")
    parser.add_argument("--iterations", type=int, default=400, help="race: most iterations per method")
    parser.add_argument("--every", type=int, default=10, help="race: write the texture every K iterations")
    parser.add_argument("--methods", default="prb,ndrf-rhs")
    parser.add_argument("--fine-tune", type=int, default=20, help="race: training steps per iteration")
    parser.add_argument("--points", type=int, default=4096, help="race: residual points per training step")
    parser.add_argument("--incident", type=int, default=16, help="race: incident samples per residual point")
    parser.add_argument("--lr", type=float, default=0.03, help="race: Adam's learning rate")
    parser.add_argument("--race-spp", type=int, default=16, help="race: spp of each iteration's render and gradient")
    parser.add_argument("--smoothness", choices=["none", "laplacian", "tv"], default="none",
                        help="race: the job's textures.smoothness")
    parser.add_argument("--weight", type=float, default=1.0, help="race: the job's textures.smoothness_weight")
    parser.add_argument("--psnr", type=float, default=17.0, help="race: a second PSNR threshold (dB) to time")
    parser.add_argument("--floor-iterations", type=int, default=20,
                        help="race: iterations at the true texture for the image loss's noise floor (0: skip)")
    parser.add_argument("--tag", default="", help="suffix of the results file's name")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    out = ROOT / "bench" / "results" / f"texture_head-{args.what}{'-' + args.tag if args.tag else ''}.json"
    if args.what == "gradient":
        result = gradient(args)
        text = (f"dz/dp of {result['scalars']} scalars (a 16 x 16 texture on the hidden floor of {SCENE}) against "
                f"prb at {result['ref_spp']} spp; the head (rank {args.rank}) trained {result['steps']} steps of "
                f"{args.points} x {args.incident} samples "
                f"({result['train_seconds']:.0f} s). The head's term is {result['head_share_of_gradient']:.0%} of "
                f"the norm of its gradient; cosine with the reference {result['cosine']:.3f}. Shared 2-core "
                f"machine.\n\n")
        text += markdown_table(["estimate", "seconds", "relative error"],
                               [[r["estimate"], r["seconds"], r["relative_error"]] for r in result["rows"]])
    else:
        rows = [race_one(m, args) for m in args.methods.split(",")]
        floor = noise_floor(args) if args.floor_iterations else None
        result = {"rows": rows, "seconds_limit": args.seconds, "noise_floor_loss": floor, "psnr": args.psnr}
        smooth = "" if args.smoothness == "none" else f", textures.smoothness {args.smoothness} {args.weight:g}"
        text = (f"Texture PSNR of {SCENE}'s hidden floor texture (16 x 16, 768 scalars) against time, Adam "
                f"{args.lr:g}{smooth}, both views at {args.race_spp} spp per iteration, at most {args.seconds:.0f} "
                f"s each; the head: rank {args.rank}, {args.steps} warm-up steps, {args.fine_tune} per iteration, "
                f"{args.points} x {args.incident} samples per step. Seconds from the plan event (targets "
                f"excluded). Shared 2-core machine.\n\n")

        def at(hit):
            return f"{hit['iteration']} ({hit['seconds']:.1f} s)" if hit else "never"

        text += markdown_table(
            ["method", "iterations", "30 dB at", f"{args.psnr:g} dB at", "best PSNR (iteration, s)",
             "image loss, last 20 iterations"],
            [[r["method"], r["iterations"], at(r["reached"]["30"]), at(r["reached"][f"{args.psnr:g}"]),
              f"{r['best']['psnr']:.2f} dB ({r['best']['iteration']}, {r['best']['seconds']:.1f} s)" if r["best"] else "-",
              r["final_loss"]] for r in rows])
        if floor is not None:
            text += (f"\n\nImage loss at the true texture (mean of {args.floor_iterations} iterations, the same "
                     f"spp): {floor:.4g}. A recovered texture whose loss is this low fits the photographs as well "
                     f"as the truth does.")
        text += "\n\nCurves (iteration, seconds, PSNR):\n\n" + "\n".join(
            f"- {r['method']}: " + ", ".join(f"({c['iteration']}, {c['seconds']:.1f}, {c['psnr']:.1f})"
                                            for c in r["curve"]) for r in rows)
    result["machine"] = machine()
    out.write_text(json.dumps(result, indent=1))
    write_markdown(out, "bench.texture_head", argv, text)


if __name__ == "__main__":
    main()

"""Texture recovery with ``prb``: a 64 x 64 albedo (12,288 scalars) on the back wall of the
textured Cornell box (``textured-box``), recovered from a 0.5 grey from 4 views; and one
iteration of a 1000 x 1000 texture (1 Mi texels, 3 Mi scalars).

``python -m bench.textures [--iterations 300] [--variants plain,laplacian,tv,coarse] [--million]``

Recovery: the 4 target views are rendered once (``--target-spp``, unbounded paths with Russian
roulette) and given to every variant as target images, so that the variants differ only in their
``textures`` settings. Each variant is the job through ``run_local`` (``method`` prb, ``optimizer``
adam with learning rate 0.03 decaying 10x, every view at 16 spp per iteration: at one view and 1 spp
Adam's steps stay noise-dominated near 20 dB in the runs made), writing its texture
every ``--every`` iterations; the texture PSNR against the true texture
(:func:`services.solver.scene.textured.true_albedo`, peak 1) is read from those files. Seconds run
on the events' clock from the plan (target rendering is outside it). Reported per variant: seconds
per iteration (median), the first written iteration at >= 30 dB and its seconds, the final PSNR.
``plain-traced`` is ``plain`` with ``render.freeze`` off (``prb`` re-traced every call), for what
replaying recorded kernels saves a texture job, measured in the same process
(``--variants plain-traced,plain --out bench/results/textures-freeze.json``).

``--loop``: Mitsuba's tutorial loop on the same job and targets (:func:`run_loops`), a row per
setting of ``--loop-spp`` x ``--loop-views``; its PSNR is measured every iteration, the product's
every ``--every``: the loop's first time at 30 dB is the sharper of the two.

``--million``: the same scene as XML with a 1000 x 1000 EXR texture and one 128 x 128 view, a job of
``--million-iterations`` iterations; reported: the iterations' seconds (median of the record's
phases), the preparation's seconds and the process's peak resident memory.
"""

from __future__ import annotations

import argparse
import base64
import json
import logging
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
KEY = "wall.reflectance.data"
VARIANTS = {
    "plain": {},
    "laplacian": {"smoothness": "laplacian", "smoothness_weight": 0.1},
    "tv": {"smoothness": "tv", "smoothness_weight": 0.03},
    "coarse": {"coarse_to_fine": 3},
    "laplacian-small": {"smoothness": "laplacian", "smoothness_weight": 0.01},
    "tv-small": {"smoothness": "tv", "smoothness_weight": 0.003},
    "one-view-1spp": {},
    "plain-traced": {},
    "every-view-4spp": {},
    "every-view-1spp": {},
    "every-view-32spp": {},
    "every-view-64spp": {},
}
#: Variants that change the batch instead of the textures settings: (job fields, iterations factor).
#: ``one-view-1spp`` is the ``auto`` batch (one view, 1 spp) for 16x the iterations: a quarter of
#: the samples of the others.
#: ``every-view-<n>spp``: every view at n spp for 16/n times the iterations (the samples of ``plain``).
#: ``plain-traced`` is ``plain`` with ``render.freeze`` off: what replaying recorded kernels saves.
BATCH = {"one-view-1spp": ({"views_per_iteration": 1, "render": {"spp": 1, "gradient_spp": 1}}, 16),
         "plain-traced": ({"render": {"spp": 16, "gradient_spp": 16, "freeze": False}}, 1),
         "every-view-4spp": ({"render": {"spp": 4, "gradient_spp": 4}}, 4),
         "every-view-1spp": ({"render": {"spp": 1, "gradient_spp": 1}}, 16),
         "every-view-32spp": ({"render": {"spp": 32, "gradient_spp": 32}}, 0.5),
         "every-view-64spp": ({"render": {"spp": 64, "gradient_spp": 64}}, 0.25)}


def _job(iterations: int, every: int, textures: dict, targets: dict, scene: dict | None = None) -> dict:
    return {"scene": scene or {"builtin": "textured-box"}, "parameters": [{"key": KEY, "init": 0.5}],
            "targets": targets, "iterations": iterations, "method": "prb", "optimizer": "adam",
            "learning_rate": 0.03, "views_per_iteration": 4, "render": {"spp": 16, "gradient_spp": 16},
            "images_every": every, "checkpoint_every": 100000, "textures": textures}


def render_targets(spp: int) -> dict:
    """The 4 views at the true texture as target images (base64 npy)."""
    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare
    from services.store.images import npy_bytes

    spec = JobSpec.model_validate(_job(1, 1, {}, {"synthetic": {"values": {KEY: None}, "spp": spp}}))
    prepared, _ = prepare(spec)
    return {"images": [{"sensor": s, "data": base64.b64encode(npy_bytes(np.asarray(image, np.float32))).decode()}
                       for s, image in sorted(prepared.targets.items())]}


def psnr(value: np.ndarray, truth: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(value, np.float64) - truth) ** 2))
    return 10.0 * float(np.log10(1.0 / mse))


def run_variant(name: str, iterations: int, every: int, targets: dict) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.solver.scene.textured import true_albedo

    truth = true_albedo().astype(np.float64)
    clock: dict[int, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        start: list[float] = []

        def on_event(event: dict) -> None:
            if event.get("type") == "plan" and not start:
                start.append(time.perf_counter())
            elif event.get("type") == "iteration":
                clock[int(event["iteration"])] = time.perf_counter() - start[0]

        fields, factor = BATCH.get(name, ({}, 1))
        job = dict(_job(max(1, int(iterations * factor)), max(1, int(every * factor)), VARIANTS[name], targets),
                   **fields)
        summary = run_local(JobSpec.model_validate(job), Path(tmp) / "job", on_event=on_event)
        folder = Path(tmp) / "job"
        curve = []
        for k in sorted(clock):
            written = folder / "iterations" / f"{k:06d}" / "textures" / f"{KEY}.npy"
            if written.exists():  # the texture the step of iteration k was taken at
                curve.append({"iteration": k, "seconds": clock[k], "psnr": psnr(np.load(written), truth)})
        final = psnr(np.load(folder / summary["textures"][KEY]["npy"]), truth)
    steps = np.diff([0.0] + [clock[k] for k in sorted(clock)])
    reached = next((c for c in curve if c["psnr"] >= 30.0), None)
    row = {"variant": name, "settings": VARIANTS[name] or fields, "status": summary["status"], "iterations": len(clock),
           "seconds": clock[max(clock)] if clock else None, "seconds_per_iteration": float(np.median(steps)),
           "reached_30db": reached, "final_psnr": final, "curve": curve}
    log.info("%s: final %.2f dB, reached 30 dB at %s", name, final, reached)
    return row


def run_loops(iterations: int, targets: dict, spps: list[int], views: list[int | None], budget: float) -> list[dict]:
    """Mitsuba's tutorial loop (:func:`bench.mitsuba_loop.run_loop`, Adam 0.03 decaying 10x, Russian
    roulette from depth 5, unfrozen) on the same job and target images, one row per setting: each
    runs as many iterations as give it the samples of ``iterations`` product iterations (every view
    at 16 spp), at most ``budget`` seconds; the texture PSNR from the RMS error of every iteration."""
    from bench.common import loop_rows
    from bench.mitsuba_loop import LoopSetting, run_loop
    from services.solver.scene.textured import true_albedo

    truth = true_albedo().astype(np.float64).reshape(-1)
    job = _job(iterations, iterations, {}, targets)
    rows = []
    for spp in spps:
        for v in views:
            setting = LoopSetting(spp, 5, v)
            views_total = job["views_per_iteration"]
            total = iterations * views_total * 16 // ((v or views_total) * spp)

            def run(prepared, setting=setting, total=total):
                run_loop(prepared, setting, target_error=0.0, iterations=2, truth=truth)   # compile, untimed
                return run_loop(prepared, setting, target_error=0.0, iterations=total, budget=budget, truth=truth)

            result, _ = loop_rows(job, run)
            curve = [{"iteration": c["iteration"], "seconds": c["seconds"], "psnr": -20.0 * float(np.log10(c["rmse"]))}
                     for c in result["curve"]]
            reached = next((c for c in curve if c["psnr"] >= 30.0), None)
            rows.append({"variant": setting.label, "settings": {"spp": spp, "views": v or views_total},
                         "iterations": len(curve), "seconds": curve[-1]["seconds"],
                         "seconds_per_iteration": result["seconds_per_iteration"], "reached_30db": reached,
                         "final_psnr": curve[-1]["psnr"], "curve": curve[:: max(1, len(curve) // 60)]})
            log.info("%s: final %.2f dB, reached 30 dB at %s", setting.label, curve[-1]["psnr"], reached)
    return rows


def run_million(iterations: int, size: int = 1000) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.solver.scene.textured import write_textured_box

    with tempfile.TemporaryDirectory() as tmp:
        scene = write_textured_box(Path(tmp) / "scene", size=size, views=1, film=128)
        job = _job(iterations, 100000, {}, {"synthetic": {"values": {KEY: None}, "spp": 4}},
                   scene={"path": str(scene)})
        job.update(views_per_iteration=1, render={"spp": 1, "gradient_spp": 1})
        started = time.perf_counter()
        summary = run_local(JobSpec.model_validate(job), Path(tmp) / "job", base_dir=Path(tmp))
        total = time.perf_counter() - started
        folder = Path(tmp) / "job"
        records = [json.loads(p.read_text()) for p in sorted(folder.glob("iterations/*/record.json"))]
        plan = json.loads((folder / "plan.json").read_text())
        final = np.load(folder / summary["textures"][KEY]["npy"])
    per_iteration = [r["seconds"]["gradient"] + r["seconds"]["step"] for r in records]
    return {"status": summary["status"], "texels": int(final.shape[0] * final.shape[1]), "shape": list(final.shape),
            "iterations": len(records), "gradient_and_step_seconds": per_iteration,
            "images_seconds": [r["seconds"]["images"] for r in records], "prepared_seconds": plan["prepared_seconds"],
            "total_seconds": total, "peak_rss_mib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}


def run_sandboxed(iterations: int, size: int) -> dict:
    """The large-texture job as the service runs it: the scene uploaded as XML with its EXR, run by
    a worker's :class:`~services.jobs.runner.AttemptRunner` in its sandboxed child (default limits)."""
    import base64
    import threading

    from schemas.job import JobSpec
    from schemas.records import JobStatus
    from services.jobs.runner import AttemptRunner
    from services.jobs.service import JobService
    from services.queue.local import LocalEventBus, LocalJobQueue
    from services.settings import Limits
    from services.solver.scene.textured import write_textured_box
    from services.store.local import FolderStore

    with tempfile.TemporaryDirectory() as tmp:
        xml = write_textured_box(Path(tmp) / "scene", size=size, views=1, film=128)
        files = {"albedo.exr": base64.b64encode((Path(tmp) / "scene" / "albedo.exr").read_bytes()).decode()}
        job = _job(iterations, 100000, {}, {"synthetic": {"values": {KEY: None}, "spp": 4}},
                   scene={"xml": xml.read_text(), "files": files})
        job.update(views_per_iteration=1, render={"spp": 1, "gradient_spp": 1})
        service = JobService(FolderStore(Path(tmp) / "store"), LocalJobQueue(), LocalEventBus())
        record, _ = service.submit(JobSpec.model_validate(job))
        service.states.transition(record.id, JobStatus.RUNNING, attempt="w#1")
        started = time.perf_counter()
        result = AttemptRunner(service.states, Limits(), Path(tmp) / "scratch").run(
            record.id, "w#1", lost=threading.Event(), stop=lambda: None)
        total = time.perf_counter() - started
        error = service.states.get(record.id).error
    return {"size": size, "status": str(result.outcome), "error": error, "total_seconds": total,
            "upload_bytes": len(files["albedo.exr"])}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.textures", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=300)
    parser.add_argument("--every", type=int, default=25, help="write (and measure) the texture every K iterations")
    parser.add_argument("--target-spp", type=int, default=1024)
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--million", action="store_true", help="also time a 1000 x 1000 texture")
    parser.add_argument("--loop", action="store_true", help="also run Mitsuba's tutorial loop on the same job")
    parser.add_argument("--loop-spp", default="1,4,16", help="the loop's spp values")
    parser.add_argument("--loop-views", default="1,all", help="the loop's views per iteration")
    parser.add_argument("--loop-budget", type=float, default=60.0, help="seconds per loop setting at most")
    parser.add_argument("--million-iterations", type=int, default=2)
    parser.add_argument("--million-size", type=int, default=1000, help="texels per side of the large texture")
    parser.add_argument("--sandboxed", action="store_true", help="also run the large texture job in a worker's "
                                                                 "sandboxed child, as the service does")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "textures.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    rows = []
    names = [v for v in args.variants.split(",") if v]
    if names:
        started = time.perf_counter()
        targets = render_targets(args.target_spp)
        log.info("targets rendered in %.1f s", time.perf_counter() - started)
        rows = [run_variant(name, args.iterations, args.every, targets) for name in names]
        if args.loop:
            rows += run_loops(args.iterations, targets, [int(x) for x in args.loop_spp.split(",")],
                              [None if x == "all" else int(x) for x in args.loop_views.split(",")], args.loop_budget)
    million = run_million(args.million_iterations, args.million_size) if args.million else None
    sandboxed = run_sandboxed(args.million_iterations, args.million_size) if args.sandboxed else None
    args.out.write_text(json.dumps({"machine": machine(), "rows": rows, "million": million, "sandboxed": sandboxed},
                                   indent=1))
    lines = [[r["variant"], json.dumps(r["settings"]) if r["settings"] else "-", r["iterations"],
              f"{r['seconds_per_iteration']:.3f}",
              f"{r['reached_30db']['iteration']} ({r['reached_30db']['seconds']:.0f} s)" if r["reached_30db"] else "never",
              f"{r['final_psnr']:.2f}", f"{r['seconds']:.0f}"] for r in rows]
    text = markdown_table(["variant", "settings", "iterations", "s / iteration", "first measured "
                           "iteration >= 30 dB", "final PSNR (dB)", "seconds"], lines) if rows else ""
    if million is not None:
        side = million["shape"][0]
        text += (f"\n\n{side} x {side} texture (" + f"{million['texels']} texels, {3 * million['texels']} scalars): "
                 f"{million['status']}; gradient + step seconds per iteration "
                 f"{', '.join(f'{s:.2f}' for s in million['gradient_and_step_seconds'])}; images (texture files) "
                 f"{', '.join(f'{s:.2f}' for s in million['images_seconds'])} s; preparation "
                 f"{', '.join(f'{k} {v:.1f} s' for k, v in million['prepared_seconds'].items())}; whole job "
                 f"{million['total_seconds']:.1f} s; peak resident memory of the process "
                 f"{million['peak_rss_mib']:.0f} MiB")
    if sandboxed is not None:
        text += (f"\n\nThe same job uploaded (XML and a {sandboxed['upload_bytes']}-byte base64 EXR) and run by a "
                 f"worker in its sandboxed child: {sandboxed['status']}"
                 + (f" ({sandboxed['error']})" if sandboxed["error"] else "")
                 + f", {sandboxed['total_seconds']:.1f} s from the attempt's start to its end")
    write_markdown(args.out, "bench.textures", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

"""A shape recovered by the product's default job against Mitsuba's shape-optimization tutorial loop.

``python -m bench.geometry --shape [--resolution 32] [--seeds 0,1,2] [--iterations 25]``

The problem: ``examples/shape.json``'s, the built-in ``shape-sphere`` (a generated icosphere of
642 vertices, 6 views) towards the sphere scaled by (1.3, 0.8, 1.0) with a bump of 0.3 radii
upwards, targets at 256 spp.

* **product**: the default job (``auto``: ``direct_projective``, uniform Adam on the LargeSteps
  coordinates, every view at 16 spp per iteration, λ 19), with ``examples/shape.json``'s learning
  rate 0.3 (in the sphere's radius), ``--iterations`` iterations, run in-process as ``ndrf run``
  runs it. Its Chamfer distance is its answer's (``summary.json``).
* **tutorial loop**: Mitsuba's ``shape_optimization`` tutorial: ``mi.ad.LargeSteps`` with λ 25,
  ``mi.ad.Adam(lr=0.1, uniform=True)`` on ``u``, one step per view (the vertices written from
  ``u`` before each render), the L1 loss, ``direct_projective`` with Mitsuba's defaults, 16 spp,
  the same targets (``--loop-guiding none``: without the guide of the indirect boundary samples,
  as the product renders). It runs for the product's wall-clock time of the same seed (equal compute),
  at least one pass over the views; its answer is its last ``u``.

Per run: the final Chamfer distance (symmetric, mean nearest-vertex distance in scene units,
:func:`services.solver.scene.shape.chamfer`), seconds, iterations (passes over the views for the
loop), the curve. Results: ``bench/results/geometry-shape-sphere.json|.md``.
"""

from __future__ import annotations

import copy
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "shape.json"
#: The tutorial's settings.
LOOP_LAMBDA, LOOP_LR, LOOP_SPP = 25.0, 0.1, 16


def shape_job(resolution: int, iterations: int, seed: int) -> dict:
    job = json.loads(EXAMPLE.read_text())
    job.pop("name", None)
    return job | {"iterations": iterations, "seed": seed, "render": {"resolution": [resolution, resolution]}}


def run_product(job: dict, folder: Path) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    started = time.perf_counter()
    summary = run_local(JobSpec.model_validate(job), folder, base_dir=folder)
    seconds = time.perf_counter() - started
    plan = json.loads((folder / "plan.json").read_text())
    curve = [[r["iteration"], r["shapes"]["sphere"]["chamfer"]]
             for r in (json.loads(p.read_text()) for p in sorted(folder.glob("iterations/*/record.json")))]
    mesh = (summary.get("meshes") or {}).get("sphere", {})
    return {"seconds": seconds, "status": summary["status"], "error": summary.get("error"),
            "chamfer": mesh.get("chamfer", float("nan")), "last_chamfer": curve[-1][1] if curve else None,
            "curve": curve, "iterations": summary["iterations"], "method": plan["recipe"]["method"],
            "optimizer": plan["recipe"]["optimizer"]}


def run_loop(job: dict, seconds: float, guiding: str | None = None) -> dict:
    """The tutorial's loop (module docstring) for ``seconds`` of wall-clock time."""
    import drjit as dr
    import mitsuba as mi

    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare
    from services.solver.scene.shape import Surface, chamfer

    prepared, _ = prepare(JobSpec.model_validate(job))
    scene, params = prepared.problem.scene.scene, prepared.problem.scene.params
    mesh = prepared.problem.parameters.shapes["sphere"]
    key = "sphere.vertex_positions"
    ls = mi.ad.LargeSteps(params[key], params["sphere.faces"], LOOP_LAMBDA)
    opt = mi.ad.Adam(lr=LOOP_LR, uniform=True)
    opt["u"] = ls.to_differential(params[key])
    integrator = mi.load_dict({"type": "direct_projective", **({"guiding": guiding} if guiding else {})})
    targets = {s: mi.TensorXf(np.asarray(image, np.float32)) for s, image in prepared.targets.items()}
    curve, started, it = [], time.perf_counter(), 0
    while it < 1 or time.perf_counter() - started < seconds:
        for sensor, target in targets.items():
            params[key] = ls.from_differential(opt["u"])
            params.update()
            image = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=LOOP_SPP, seed=it)
            dr.backward(dr.mean(dr.abs(image[..., :3] - target)))
            opt.step()
        vertices = np.asarray(ls.from_differential(dr.detach(opt["u"])), np.float64).reshape(-1, 3)
        curve.append([it, chamfer(Surface(vertices, mesh.faces), mesh.target), time.perf_counter() - started])
        it += 1
    return {"seconds": time.perf_counter() - started, "iterations": it, "chamfer": curve[-1][1],
            "best_chamfer": min(row[1] for row in curve), "curve": curve,
            "settings": {"integrator": f"direct_projective ({'guiding ' + guiding if guiding else 'defaults'})",
                         "spp": LOOP_SPP, "lr": LOOP_LR,
                         "optimizer": "mi.ad.Adam(uniform=True), one step per view", "lambda": LOOP_LAMBDA,
                         "loss": "l1"}}


def main_shape(args, argv: list[str] | None) -> None:
    """``bench.geometry --shape`` (module docstring)."""
    runs, rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            job = shape_job(args.resolution, args.iterations, seed)
            product = run_product(copy.deepcopy(job), Path(tmp) / f"product-{seed}")
            loop = run_loop(job, product["seconds"], args.loop_guiding)
            runs.append({"seed": seed, "product": product, "loop": loop})
            start = product["curve"][0][1] if product["curve"] else float("nan")
            rows += [[f"product ({product['method']}, {product['optimizer']} uniform)", seed, f"{start:.4f}",
                      f"{product['chamfer']:.4f}", f"{product['seconds']:.0f}", product["iterations"], ""],
                     ["tutorial loop (LargeSteps, Adam uniform)", seed, f"{start:.4f}", f"{loop['chamfer']:.4f}",
                      f"{loop['seconds']:.0f}", loop["iterations"], f"{loop['best_chamfer']:.4f}"]]
            log.info("seed %d: product %.4f, loop %.4f", seed, product["chamfer"], loop["chamfer"])
    summary = {}
    for who in ("product", "loop"):
        values = np.array([run[who]["chamfer"] for run in runs], np.float64)
        summary[who] = {"chamfer_median": float(np.median(values)),
                        "chamfer_range": [float(values.min()), float(values.max())]}
    result = {"scene": "shape-sphere", "resolution": args.resolution, "iterations": args.iterations,
              "job": shape_job(args.resolution, args.iterations, 0), "machine": machine(), "runs": runs,
              "summary": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    name = "geometry-shape-sphere" + (f"-guiding-{args.loop_guiding}" if args.loop_guiding else "")
    (args.out / f"{name}.json").write_text(json.dumps(result, indent=1))
    table = markdown_table(["run", "seed", "Chamfer at the start", "final Chamfer", "seconds",
                            "iterations (loop: passes over the views)", "loop's best on the way"], rows)
    medians = "\n".join(f"- {who}: {s['chamfer_median']:.4f} (range {s['chamfer_range'][0]:.4f}-"
                        f"{s['chamfer_range'][1]:.4f})" for who, s in summary.items())
    text = (f"# Shape: the product's default against the tutorial loop (shape-sphere, {args.resolution}x"
            f"{args.resolution}, 6 views)\n\nEqual compute: the loop runs for the product's seconds of the same "
            f"seed. Chamfer distance in scene units (the sphere's radius is 0.4). The loop's integrator: "
            f"{runs[0]['loop']['settings']['integrator']}.\n\n{table}\n\n"
            f"Medians over the seeds:\n\n{medians}\n")
    write_markdown(args.out / f"{name}.md", "bench.geometry", argv, text)

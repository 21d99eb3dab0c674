"""A shape recovered by the product's default job against Mitsuba's shape-optimization tutorial loop.

``python -m bench.geometry --shape [--resolution 32] [--seeds 0,1,2] [--iterations 25]
[--target deformed|rounded-box] [--remesh-at F] [--loop-guiding none]``

The problem: ``examples/shape.json``'s scene, the built-in ``shape-sphere`` (a generated,
smooth-shaded icosphere of 642 vertices, 6 views), targets at 256 spp, towards

* ``deformed`` (default): the sphere scaled by (1.3, 0.8, 1.0) with a bump of 0.3 radii upwards
  (``examples/shape.json``: the same triangles);
* ``rounded-box``: the built-in rounded box (866 vertices on a cube's grid: another topology, as
  the tutorial's Suzanne is to its icosphere), its corners at the sphere's radius.

* **product**: the default job (``auto``: ``direct-projective``, uniform Adam on the LargeSteps
  coordinates, every view at 16 spp per iteration, λ 19), with ``examples/shape.json``'s learning
  rate 0.3 (in the sphere's radius), ``--iterations`` iterations, run in-process as ``ndrf run``
  runs it; with ``--remesh-at F`` its ``geometry.remesh_at`` is ``[round(F x iterations)]``. Its
  Chamfer distance is its answer's (``summary.json``).
* **tutorial loop**: Mitsuba's ``shape_optimization`` tutorial: ``mi.ad.LargeSteps`` with λ 25,
  ``mi.ad.Adam(lr=0.1, uniform=True)`` on ``u``, one step per view (the vertices written from
  ``u`` before each render), the L1 loss, ``direct-projective`` with ``sppi: 0`` (the tutorial's
  first stage), 16 spp, the same targets. With ``--remesh-at F``, after ``F`` of its seconds it
  remeshes as the tutorial does (``gpytoolbox.remesh_botsch``, 5 passes, to half the mean edge
  length), starts a new ``LargeSteps`` and ``Adam`` and, as the tutorial's second stage, renders
  with ``direct-projective``'s defaults (``--loop-guiding``: its guiding) and steps once per
  pass over the views. It runs for the product's wall-clock time of the same seed (equal
  compute; the seconds its Chamfer distances take are not counted), at least one pass over the
  views; its answer is its last ``u``.

Per run: the final Chamfer distance between surfaces (scene units,
:func:`services.solver.scene.shape.chamfer`), seconds, iterations (passes over the views for the
loop), the vertices at the end, the curve. Results: ``bench/results/geometry-shape-<target>
[-remesh][-guiding-<g>].json|.md``.
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
LOOP_LAMBDA, LOOP_LR, LOOP_SPP, LOOP_EDGE, LOOP_PASSES = 25.0, 0.1, 16, 0.5, 5


def shape_job(resolution: int, iterations: int, seed: int, target: str = "deformed",
              remesh_at: float | None = None) -> dict:
    job = json.loads(EXAMPLE.read_text())
    job.pop("name", None)
    job = job | {"iterations": iterations, "seed": seed, "render": {"resolution": [resolution, resolution]}}
    if target == "rounded-box":
        job["targets"]["synthetic"]["meshes"] = {"sphere": {"builtin": "rounded-box"}}
    if remesh_at is not None:
        job["geometry"] = {**job.get("geometry", {}), "remesh_at": [max(1, round(remesh_at * iterations))]}
    return job


def run_product(job: dict, folder: Path) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    started = time.perf_counter()
    summary = run_local(JobSpec.model_validate(job), folder, base_dir=folder)
    seconds = time.perf_counter() - started
    plan = json.loads((folder / "plan.json").read_text())
    records = [json.loads(p.read_text()) for p in sorted(folder.glob("iterations/*/record.json"))]
    curve = [[r["iteration"], r["shapes"]["sphere"]["chamfer"]] for r in records]
    mesh = (summary.get("meshes") or {}).get("sphere", {})
    return {"seconds": seconds, "status": summary["status"], "error": summary.get("error"),
            "chamfer": mesh.get("chamfer", float("nan")), "last_chamfer": curve[-1][1] if curve else None,
            "vertices": mesh.get("vertices"), "curve": curve, "iterations": summary["iterations"],
            "method": plan["recipe"]["method"], "optimizer": plan["recipe"]["optimizer"],
            "events": [e for e in plan["events"] if e["what"] == "remesh"]}


def run_loop(job: dict, seconds: float, guiding: str | None = None, remesh_at: float | None = None) -> dict:
    """The tutorial's loop (module docstring) for ``seconds`` of compute."""
    import drjit as dr
    import mitsuba as mi

    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare
    from services.solver.scene.remesh import remesh
    from services.solver.scene.shape import Surface, chamfer, write_topology

    prepared, _ = prepare(JobSpec.model_validate(job))
    scene, params = prepared.problem.scene.scene, prepared.problem.scene.params
    target = prepared.problem.parameters.shapes["sphere"].target
    key = "sphere.vertex_positions"
    second = {"type": "direct_projective", **({"guiding": guiding} if guiding else {})}
    integrator = mi.load_dict({"type": "direct_projective", "sppi": 0})
    targets = {s: mi.TensorXf(np.asarray(image, np.float32)) for s, image in prepared.targets.items()}

    def start() -> tuple:
        steps = mi.ad.LargeSteps(params[key], params["sphere.faces"], LOOP_LAMBDA)
        adam = mi.ad.Adam(lr=LOOP_LR, uniform=True)
        adam["u"] = steps.to_differential(params[key])
        return steps, adam

    ls, opt = start()
    curve, spent, it, remeshed = [], 0.0, 0, remesh_at is None
    while it < 1 or spent < seconds:
        lap = time.perf_counter()
        if not remeshed and spent >= remesh_at * seconds:   # the tutorial's remesh, then its second stage
            params[key] = ls.from_differential(opt["u"])
            params.update()
            faces = np.asarray(params["sphere.faces"], np.int64).reshape(-1, 3)
            new = remesh(np.asarray(params[key], np.float64).reshape(-1, 3), faces, LOOP_EDGE, LOOP_PASSES)
            write_topology(params, "sphere", new.vertices, new.faces)
            ls, opt = start()
            integrator, remeshed = mi.load_dict(second), True
        for sensor, image_target in targets.items():
            params[key] = ls.from_differential(opt["u"])
            params.update()
            image = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=LOOP_SPP, seed=it)
            dr.backward(dr.mean(dr.abs(image[..., :3] - image_target)))
            if remesh_at is None or not remeshed:
                opt.step()    # the first stage: one step per view
        if remeshed and remesh_at is not None:
            opt.step()        # the second stage: one step per pass over the views
        spent += time.perf_counter() - lap
        vertices = np.asarray(ls.from_differential(dr.detach(opt["u"])), np.float64).reshape(-1, 3)
        faces = np.asarray(params["sphere.faces"], np.int64).reshape(-1, 3)
        curve.append([it, chamfer(Surface(vertices, faces), target), spent])
        it += 1
    return {"seconds": spent, "iterations": it, "chamfer": curve[-1][1], "vertices": len(vertices),
            "best_chamfer": min(row[1] for row in curve), "curve": curve,
            "settings": {"integrator": "direct-projective (sppi 0" + (
                f"; after the remesh {'guiding ' + guiding if guiding else 'its defaults'})" if remesh_at is not None
                else ")"), "spp": LOOP_SPP, "lr": LOOP_LR, "lambda": LOOP_LAMBDA, "loss": "l1",
                "optimizer": "mi.ad.Adam(uniform=True), one step per view" + (
                    "; after the remesh one per pass" if remesh_at is not None else ""),
                "remesh": None if remesh_at is None else {"at_share_of_seconds": remesh_at, "edge": LOOP_EDGE,
                                                          "passes": LOOP_PASSES}}}


def main_shape(args, argv: list[str] | None) -> None:
    """``bench.geometry --shape`` (module docstring)."""
    runs, rows = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for seed in (int(s) for s in args.seeds.split(",")):
            job = shape_job(args.resolution, args.iterations, seed, args.target, args.remesh_at)
            product = run_product(copy.deepcopy(job), Path(tmp) / f"product-{seed}")
            loop = run_loop(job, product["seconds"], args.loop_guiding, args.remesh_at)
            runs.append({"seed": seed, "product": product, "loop": loop})
            start = product["curve"][0][1] if product["curve"] else float("nan")
            rows += [[f"product ({product['method']}, {product['optimizer']} uniform)", seed, f"{start:.4f}",
                      f"{product['chamfer']:.4f}", f"{product['seconds']:.0f}", product["iterations"],
                      product["vertices"], ""],
                     ["tutorial loop (LargeSteps, Adam uniform)", seed, f"{start:.4f}", f"{loop['chamfer']:.4f}",
                      f"{loop['seconds']:.0f}", loop["iterations"], loop["vertices"], f"{loop['best_chamfer']:.4f}"]]
            log.info("seed %d: product %.4f, loop %.4f", seed, product["chamfer"], loop["chamfer"])
    summary = {}
    for who in ("product", "loop"):
        values = np.array([run[who]["chamfer"] for run in runs], np.float64)
        summary[who] = {"chamfer_median": float(np.median(values)),
                        "chamfer_range": [float(values.min()), float(values.max())]}
    job = shape_job(args.resolution, args.iterations, 0, args.target, args.remesh_at)
    result = {"scene": "shape-sphere", "target": args.target, "resolution": args.resolution,
              "iterations": args.iterations, "remesh_at": args.remesh_at, "job": job, "machine": machine(),
              "runs": runs, "summary": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    name = ("geometry-shape-sphere" if args.target == "deformed" else f"geometry-shape-{args.target}") + (
        "-remesh" if args.remesh_at is not None else "") + (f"-guiding-{args.loop_guiding}" if args.loop_guiding else "")
    (args.out / f"{name}.json").write_text(json.dumps(result, indent=1))
    table = markdown_table(["run", "seed", "Chamfer at the start", "final Chamfer", "seconds",
                            "iterations (loop: passes over the views)", "vertices at the end",
                            "loop's best on the way"], rows)
    medians = "\n".join(f"- {who}: {s['chamfer_median']:.4f} (range {s['chamfer_range'][0]:.4f}-"
                        f"{s['chamfer_range'][1]:.4f})" for who, s in summary.items())
    remeshing = ("" if args.remesh_at is None else
                 f" Both remesh once: the product before iteration {job['geometry']['remesh_at'][0]}, the loop after "
                 f"{args.remesh_at:g} of its seconds.")
    text = (f"# Shape: the product's default against the tutorial loop (shape-sphere to {args.target}, "
            f"{args.resolution}x{args.resolution}, 6 views)\n\nEqual compute: the loop runs for the product's seconds "
            f"of the same seed.{remeshing} Chamfer distance between the surfaces, in scene units (the sphere's radius "
            f"is 0.4). The loop's integrator: {runs[0]['loop']['settings']['integrator']}.\n\n{table}\n\n"
            f"Medians over the seeds:\n\n{medians}\n")
    write_markdown(args.out / f"{name}.md", "bench.geometry", argv, text)

"""A pose recovered by the product's default job against Mitsuba's pose-estimation tutorial loop.

``python -m bench.geometry [--mesh PLY] [--resolution 64] [--seeds 0,1,2] [--iterations 20]
[--loop-lr 0.025] [--loop-against RESULTS.json]``

(``--shape``: a mesh's shape instead, against the shape-optimization tutorial loop:
:mod:`bench.geometry_shape`.)

The problem (issue 34): a mesh on a floor under an area light, two views, the targets rendered
with every bounce (256 spp), and a pose 0.06 off in translation (``[0.042, 0, -0.042]``) and 15
degrees about the vertical axis. ``--mesh`` names a PLY (the issue's bunny); without it the
generated block of the built-in ``pose-block``.

* **product**: the default job (``auto``: its method, optimizer, batch and steps, as ``plan.json``
  records them), ``--iterations`` iterations, run in-process as ``ndrf run`` runs it.
* **tutorial loop**: Mitsuba's ``object_pose_estimation`` tutorial, generalised to the 6 pose
  scalars: ``mi.ad.Adam(lr=0.025)`` on the translation and on the Euler angles in units of 100
  degrees (the tutorial's scale of its angle), the vertices moved by ``mi.Transform4f`` about the
  mesh's centre, ``prb-projective`` with Mitsuba's defaults (its guide included), 16 spp, both
  views per iteration, the mean squared error summed over the views. It runs for the product's
  wall-clock time of the same seed (equal compute), at least 2 iterations. ``--loop-lr`` sweeps
  its learning rate (the best setting of the loop a user would write); ``--loop-against`` runs
  the loop alone, for the product's seconds of each seed as an earlier results file records them
  (same machine), written as ``geometry-<scene>-loop-lr<lr>``.

Per run: the final translation error (Euclidean, scene units), the rotation error (the largest
of the three angles, degrees), seconds, iterations, and for the loop its best error on the way
(a loop that got there and left diverged). Results: ``bench/results/geometry-<scene>.json|.md``.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

TRUTH_TRANSLATE = [0.042, 0.0, -0.042]   # 0.06 from the start
TRUTH_ROTATE = [0.0, 15.0, 0.0]
#: The tutorial's settings.
LOOP_LR, LOOP_SPP, ANGLE_SCALE = 0.025, 16, 100.0


def _scene(mesh: Path | None, resolution: int, folder: Path) -> tuple[dict, str]:
    """The job's scene and the posed shape's id: the built-in ``pose-block``, or ``mesh`` on the
    same floor under the same light (an XML scene written into ``folder``)."""
    if mesh is None:
        return {"builtin": "pose-block"}, "block"
    (folder / "mesh.ply").write_bytes(mesh.read_bytes())
    camera = ('<sensor type="perspective"><float name="fov" value="35"/><transform name="to_world">'
              '<lookat origin="{o}" target="0, 0.1, 0" up="0, 1, 0"/></transform>'
              f'<film type="hdrfilm"><integer name="width" value="{resolution}"/>'
              f'<integer name="height" value="{resolution}"/><rfilter type="box"/>'
              '<boolean name="sample_border" value="true"/></film></sensor>')
    xml = ('<scene version="3.0.0"><integrator type="path"/>'
           + camera.format(o="0.3, 0.5, 0.8") + camera.format(o="0.8, 0.5, -0.2")
           + '<shape type="rectangle" id="floor"><transform name="to_world"><rotate x="1" angle="-90"/>'
             '<scale value="2"/></transform><bsdf type="diffuse"/></shape>'
           + '<shape type="ply" id="mesh"><string name="filename" value="mesh.ply"/>'
             '<bsdf type="diffuse"><rgb name="reflectance" value="0.7, 0.5, 0.3"/></bsdf></shape>'
           + '<shape type="rectangle" id="light"><transform name="to_world"><scale value="0.3"/>'
             '<lookat origin="0.3, 1.5, 0.5" target="0, 0, 0" up="0, 0, 1"/></transform>'
             '<emitter type="area"><rgb name="radiance" value="25"/></emitter></shape></scene>')
    (folder / "scene.xml").write_text(xml)
    return {"path": str(folder / "scene.xml")}, "mesh"


def _job(scene: dict, shape: str, resolution: int, iterations: int, seed: int) -> dict:
    keys = [f"{shape}.to_world.translate", f"{shape}.to_world.rotate"]
    return {"scene": scene, "parameters": [{"key": key} for key in keys],
            "targets": {"synthetic": {"values": {keys[0]: TRUTH_TRANSLATE, keys[1]: TRUTH_ROTATE}, "spp": 256}},
            "iterations": iterations, "render": {"resolution": [resolution, resolution]}, "seed": seed}


def pose_error(values) -> tuple[float, float]:
    """(translation error, Euclidean; rotation error, the largest angle's, degrees) of ``values`` (6,)."""
    values = np.asarray(values, np.float64)
    return (float(np.linalg.norm(values[:3] - TRUTH_TRANSLATE)), float(np.max(np.abs(values[3:] - TRUTH_ROTATE))))


def run_product(job: dict, folder: Path) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    started = time.perf_counter()
    summary = run_local(JobSpec.model_validate(job), folder, base_dir=folder)
    seconds = time.perf_counter() - started
    plan = json.loads((folder / "plan.json").read_text())
    curve = []
    for path in sorted(folder.glob("iterations/*/record.json")):
        record = json.loads(path.read_text())
        curve.append([record["iteration"], *pose_error(record["parameters"])])
    final = summary.get("estimate") or [np.nan] * 6
    return {"seconds": seconds, "status": summary["status"], "error": summary.get("error"),
            "final": final, "final_error": pose_error(final), "curve": curve, "iterations": summary["iterations"],
            "method": plan["recipe"]["method"], "optimizer": plan["recipe"]["optimizer"],
            "standard_error": summary.get("standard_error"), "stopped": (summary.get("stopped") or {}).get("reason")}


def run_loop(job: dict, shape: str, seconds: float, folder: Path, lr: float = LOOP_LR) -> dict:
    """The tutorial's loop (module docstring) for ``seconds`` of wall-clock time."""
    import drjit as dr
    import mitsuba as mi

    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare

    spec = JobSpec.model_validate(job)
    scene_file = Path(job["scene"]["path"]) if "path" in job["scene"] else None
    prepared, _ = prepare(spec, scene_file=scene_file)
    scene, params = prepared.problem.scene.scene, prepared.problem.scene.params
    prepared.problem.parameters.assign(np.zeros(6))
    key = f"{shape}.vertex_positions"
    v0 = dr.unravel(mi.Point3f, params[key])
    first = np.asarray(params[key], np.float64).reshape(-1, 3)
    centre = (first.min(axis=0) + first.max(axis=0)) / 2
    integrator = mi.load_dict({"type": "prb_projective"})
    targets = {s: mi.TensorXf(np.asarray(image, np.float32)) for s, image in prepared.targets.items()}
    opt = mi.ad.Adam(lr=lr)
    opt["t"], opt["a"] = mi.Vector3f(0, 0, 0), mi.Vector3f(0, 0, 0)
    curve, started, it = [], time.perf_counter(), 0
    while it < 2 or time.perf_counter() - started < seconds:
        a = opt["a"] * ANGLE_SCALE
        trafo = (mi.Transform4f().translate(mi.Vector3f(*(float(x) for x in centre)) + opt["t"]).rotate([0, 0, 1], a.z)
                 .rotate([0, 1, 0], a.y).rotate([1, 0, 0], a.x).translate(mi.Vector3f(*(float(-x) for x in centre))))
        params[key] = dr.ravel(trafo @ v0)
        params.update()
        losses = []
        for sensor, target in targets.items():
            image = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=LOOP_SPP,
                              seed=dr.opaque(mi.UInt32, 1000 * it + sensor))
            losses.append(dr.mean(dr.square(image[..., :3] - target)))
        dr.backward(sum(losses[1:], losses[0]))
        opt.step()
        values = np.concatenate([np.asarray(opt["t"], np.float64).reshape(-1),
                                 ANGLE_SCALE * np.asarray(opt["a"], np.float64).reshape(-1)])
        curve.append([it, *pose_error(values), time.perf_counter() - started])
        it += 1
    final = curve[-1]
    best = min(curve, key=lambda row: row[1] / 0.01 + row[2])
    return {"seconds": time.perf_counter() - started, "iterations": it, "final_error": final[1:3],
            "best_error": best[1:3], "best_iteration": best[0], "curve": curve,
            "settings": {"integrator": "prb-projective (Mitsuba's defaults, guiding octree)", "spp": LOOP_SPP,
                         "lr": lr, "optimizer": "mi.ad.Adam", "angle_scale_degrees": ANGLE_SCALE}}


def _row(label: str, seed: int, run: dict) -> list:
    t, r = run["final_error"]
    best = run.get("best_error")
    extra = "" if best is None else f"{best[0]:.4f} / {best[1]:.2f} at {run['best_iteration']}"
    return [label, seed, f"{t:.4f}", f"{r:.2f}", f"{run['seconds']:.0f}", run["iterations"], extra]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.geometry", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--mesh", type=Path, default=None, help="a PLY mesh (default: the generated block)")
    parser.add_argument("--resolution", type=int, default=64)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--iterations", type=int, default=20, help="the product's iterations")
    parser.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "results")
    parser.add_argument("--shape", action="store_true", help="the shape case (bench.geometry_shape): "
                                                              "examples/shape.json against the LargeSteps loop")
    parser.add_argument("--loop-guiding", default=None, help="--shape: the loop integrator's guiding "
                                                                  "(default: Mitsuba's; 'none' as the product)")
    parser.add_argument("--target", default="deformed", choices=["deformed", "rounded-box"],
                        help="--shape: the target shape (examples/shape.json's deformed sphere, or the built-in "
                             "rounded box: another topology)")
    parser.add_argument("--remesh-at", type=float, default=None, help="--shape: remesh once, the product before "
                                                                      "this share of its iterations, the loop after "
                                                                      "this share of its seconds (the tutorial's)")
    parser.add_argument("--no-loop", action="store_true", help="the product alone (a budget the loop was not "
                                                               "raced at); the results file is named '-product'")
    parser.add_argument("--loop-lr", type=float, default=LOOP_LR, help="the loop's Adam learning rate (the "
                                                                        "tutorial's 0.025)")
    parser.add_argument("--loop-against", type=Path, default=None,
                        help="the loop alone, for the product's seconds of each seed in this earlier results file")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    from services.solver.backend import use_mitsuba

    use_mitsuba()
    if args.shape:
        from bench.geometry_shape import main_shape

        main_shape(args, argv)
        return
    name = "pose-block" if args.mesh is None else args.mesh.stem
    runs: list[dict] = []
    rows: list[list] = []
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        scene, shape = _scene(args.mesh, args.resolution, folder)
        earlier = ({run["seed"]: run["product"] for run in json.loads(args.loop_against.read_text())["runs"]}
                   if args.loop_against else {})
        for seed in (int(s) for s in args.seeds.split(",")):
            job = _job(scene, shape, args.resolution, args.iterations, seed)
            product = earlier[seed] if args.loop_against else run_product(job, folder / f"product-{seed}")
            runs.append({"seed": seed, "product": product})
            rows.append(_row(f"product ({product['method']}, {product['optimizer']})"
                             + (f", from {args.loop_against.name}" if args.loop_against else ""), seed, product))
            if not args.no_loop:
                loop = runs[-1]["loop"] = run_loop(job, shape, product["seconds"], folder, args.loop_lr)
                rows.append(_row(f"tutorial loop (Adam {args.loop_lr:g})", seed, loop))
            log.info("seed %d: product %s, loop %s", seed, product["final_error"],
                     runs[-1]["loop"]["final_error"] if "loop" in runs[-1] else "not run")
    if args.no_loop:
        name += f"-product-{args.iterations}"
    elif args.loop_against or args.loop_lr != LOOP_LR:
        name += f"-loop-lr{args.loop_lr:g}"
    summary: dict[str, dict] = {}
    for who in ("product",) if args.no_loop else ("product", "loop"):
        errors = np.array([run[who]["final_error"] for run in runs], np.float64)
        summary[who] = {"translation_median": float(np.median(errors[:, 0])),
                        "translation_range": [float(errors[:, 0].min()), float(errors[:, 0].max())],
                        "rotation_median": float(np.median(errors[:, 1])),
                        "rotation_range": [float(errors[:, 1].min()), float(errors[:, 1].max())]}
    result = {"scene": name, "resolution": args.resolution, "iterations": args.iterations,
              "truth": {"translate": TRUTH_TRANSLATE, "rotate": TRUTH_ROTATE}, "machine": machine(),
              "runs": runs, "summary": summary}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / f"geometry-{name}.json").write_text(json.dumps(result, indent=1))
    table = markdown_table(["run", "seed", "translation error", "rotation error (deg)", "seconds", "iterations",
                            "loop's best (translation / deg, at iteration)"], rows)
    medians = "\n".join(f"- {who}: translation {s['translation_median']:.4f} (range {s['translation_range'][0]:.4f}-"
                        f"{s['translation_range'][1]:.4f}), rotation {s['rotation_median']:.2f} deg (range "
                        f"{s['rotation_range'][0]:.2f}-{s['rotation_range'][1]:.2f})" for who, s in summary.items())
    raced = ("Equal compute: the loop runs for the product's seconds of the same seed"
             + (f" as {args.loop_against.name} records them (the product's rows are copied from it)."
                if args.loop_against else ".") if not args.no_loop else
             "The product alone (--no-loop): the loop was not run at this budget.")
    text = (f"# Pose: the product's default against the tutorial loop ({name}, {args.resolution}x"
            f"{args.resolution}, 2 views)\n\n{raced}\n\n{table}\n\nMedians over the seeds:\n\n{medians}\n")
    write_markdown(args.out / f"geometry-{name}.md", "bench.geometry", argv, text)


if __name__ == "__main__":
    main()

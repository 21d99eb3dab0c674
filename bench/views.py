"""View independence of ``dL_theta`` (paper Sec. 7.1, Fig. 4b): after a short NDRF job, the
field's gradient images from three cameras none of the job's sensors had, against ``prb`` at
high spp from the same camera, next to the same error at the job's own sensor; seconds per view.

For each scene (``examples/cornell-red.json``, ``examples/hidden-object.json``, shortened to
``--iterations``) the job runs in-process into a scratch folder; its checkpoint is restored
(:func:`services.solver.optimize.field_views.restore`) and each camera rendered
(:func:`~services.solver.optimize.field_views.render_view`): the field's ``(P, H, W, 3)``
gradient images at ``--spp`` first-hit samples, ``prb``'s at ``--prb-spp``. ``error`` is the
relative L2 error over every scalar's image; ``sum_error`` that of the pixel sums (``(P, 3)``:
what a loss weighing every pixel alike sees, where the per-pixel noise averages out). ``prb``'s
own noise at ``--prb-spp`` is in both (``prb_noise``: two ``prb`` images with different seeds at
that spp, relative to each other, divided by √2). Seconds per view: the field's view (scene
rebuilt with the camera, first hits traced, fields queried) at the job's resolution and at 128x128,
and the same 128x128 view once more (what an orbit viewer's next frame would cost once Dr.Jit's
kernels are compiled). Timings taken while other processes share the cores are upper bounds.

    python -m bench.views [--iterations 12] [--prb-spp 1024] [--scenes cornell-red,hidden-object]
                          [--warmup-steps N] [--residual-points N]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

from bench.common import machine, markdown_table, relative_error, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent

#: Three cameras per scene that no sensor of the job had (and the job's own sensor, ``sensor: 0``).
CAMERAS = {
    "cornell-red": {
        "own sensor": {"sensor": 0},
        "right, higher": {"origin": [0.9, 0.5, 3.6], "target": [0.0, 0.0, 0.0], "fov": 32},
        "left, closer": {"origin": [-0.6, -0.2, 2.4], "target": [0.2, 0.0, 0.0], "fov": 48},
        "inside, above": {"origin": [0.0, 0.6, 0.9], "target": [0.0, -0.4, -1.0], "fov": 75},
    },
    "hidden-object": {
        "own sensor": {"sensor": 0},
        "sensor moved (0.3, 0.2, 0)": {"sensor": 0, "offset": [0.3, 0.2, 0.0]},
        "back corner, sphere in view": {"origin": [-0.7, 0.5, -0.7], "target": [0.2, -0.5, 1.0], "fov": 70},
        "front corner, facing back": {"origin": [0.8, -0.4, 1.4], "target": [-0.5, 0.0, -0.8], "fov": 70},
    },
}


def _job(name: str, iterations: int, training: dict) -> dict:
    job = json.loads((ROOT / "examples" / f"{name}.json").read_text())
    job["iterations"] = iterations
    job["training"] = {**job.get("training", {}), **training}
    job["images_every"] = iterations  # images off the clock (the view does not need them)
    return job


def measure(name: str, iterations: int, spp: int, prb_spp: int, training: dict | None = None) -> dict:
    from schemas.job import JobSpec
    from schemas.views import ViewRequest
    from services.jobs.local import run_local
    from services.solver.optimize.field_views import render_view, restore

    job = _job(name, iterations, training or {})
    folder = Path(tempfile.mkdtemp(prefix=f"bench-views-{name}-"))
    try:
        spec = JobSpec.model_validate(job)
        started = time.perf_counter()
        summary = run_local(spec, folder / "job")
        job_seconds = time.perf_counter() - started
        if summary["status"] != "succeeded":
            raise RuntimeError(f"{name}: the job {summary['status']}: {summary.get('error')}")
        blob = (folder / "job" / "checkpoints" / "latest.pt").read_bytes()
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    restored = restore(spec, blob)
    rows = []
    for label, camera in CAMERAS[name].items():
        request = ViewRequest.model_validate({**camera, "spp": spp, "prb_spp": prb_spp})
        view = render_view(restored, request)
        assert view.prb is not None  # prb_spp was given
        at_128 = request.model_copy(update={"prb_spp": None, "resolution": (128, 128)})
        timed = render_view(restored, at_128)
        again = render_view(restored, at_128)  # the same camera again: kernels compiled, as an orbit's next frame
        rows.append({
            "camera": label, "request": camera,
            "error": relative_error(view.gradients, view.prb),
            "sum_error": relative_error(view.gradients.sum(axis=(1, 2)), view.prb.sum(axis=(1, 2))),
            "view_seconds": view.seconds["scene"] + view.seconds["fields"],
            "view_seconds_128": timed.seconds["scene"] + timed.seconds["fields"],
            "view_seconds_128_again": again.seconds["scene"] + again.seconds["fields"],
            "prb_seconds": view.seconds["prb"], "resolution": view.camera["resolution"],
        })
        log.info("%s / %s: %s", name, label, {k: v for k, v in rows[-1].items() if k != "request"})
    return {"scene": name, "job": job, "job_seconds": job_seconds, "iteration": restored.iteration,
            "method": restored.method, "spp": spp, "prb_spp": prb_spp, "rows": rows}


def table(results: list[dict]) -> str:
    lines = [[r["scene"], row["camera"], row["error"], row["sum_error"], row["view_seconds"],
              row["view_seconds_128"], row.get("view_seconds_128_again", "-"), row["prb_seconds"]]
             for r in results for row in r["rows"]]
    return markdown_table(["job", "camera", "error vs prb", "pixel-sum error",
                           "s / view (job res.)", "s / view 128x128", "s / same view again", "s prb"], lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.views", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scenes", default="cornell-red,hidden-object")
    parser.add_argument("--iterations", type=int, default=12, help="iterations of each job (short)")
    parser.add_argument("--spp", type=int, default=16, help="first-hit samples per pixel of the field's view")
    parser.add_argument("--prb-spp", type=int, default=1024, help="prb's samples per pixel (the issue: 4096)")
    parser.add_argument("--warmup-steps", type=int, default=None, help="override the jobs' training.warmup_steps")
    parser.add_argument("--residual-points", type=int, default=None,
                        help="override the jobs' training.residual_points")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    training = {k: v for k, v in (("warmup_steps", args.warmup_steps), ("residual_points", args.residual_points))
                if v is not None}
    results = [measure(name, args.iterations, args.spp, args.prb_spp, training)
               for name in args.scenes.split(",") if name]
    out = args.out or ROOT / "bench" / "results" / "views.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps({"machine": machine(), "results": results}, indent=1))
    text = table(results)
    write_markdown(out, "bench.views", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

"""Response time of ``POST /v1/jobs/{id}/views`` as the dashboard's orbit viewer sees it: a real
``ndrf serve`` (embedded), a short job of ``--scene`` trained first, then views from cameras
orbiting sensor 0's target point, each timed around its HTTP request (the view, the PNGs, the
JSON; ``inline``: nothing stored).

* ``first``: the first view of the job (the API starts the job's sandboxed view child: Python,
  Mitsuba and torch imported, scene loaded, checkpoint restored, kernels compiled);
* ``warm 128x128`` / ``warm 64x64, 1 spp``: the next views, answered by that warm child;
* ``one-off 128x128``: the same views from a second ``ndrf serve`` with
  ``NDRF_VIEW_KEEP_SECONDS=0`` (every view starts its own child, as before warm children).

Timings on a machine shared with other work are upper bounds.

    python -m bench.views_api [--scene hidden-object] [--views 8] [--one-off 3]
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import shutil
import signal
import statistics
import tempfile
import time
import urllib.error
import urllib.request
from pathlib import Path

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent


def orbit(camera: dict, angle: float) -> dict:
    """``camera`` turned by ``angle`` radians about the vertical through its target."""
    (ox, oy, oz), (tx, _, tz) = camera["origin"], camera["target"]
    dx, dz = ox - tx, oz - tz
    c, s = math.cos(angle), math.sin(angle)
    return {"origin": [tx + c * dx + s * dz, oy, tz - s * dx + c * dz], "target": camera["target"],
            "up": camera["up"], "fov": camera["fov"]}


def post(api, path: str, body: dict, timeout: float = 1800.0) -> tuple[int, dict]:
    """POST JSON with a patient timeout (a starved machine takes minutes to load a scene)."""
    request = urllib.request.Request(api.base + path, data=json.dumps(body).encode(), method="POST",
                                     headers={"Content-Type": "application/json"})
    try:
        with urllib.request.urlopen(request, timeout=timeout) as response:
            return response.status, json.loads(response.read())
    except urllib.error.HTTPError as error:
        return error.code, json.loads(error.read() or b"{}")


def timed(api, path: str, body: dict) -> tuple[float, dict]:
    started = time.perf_counter()
    status, view = post(api, path, body)
    seconds = time.perf_counter() - started
    if status != 201:
        raise RuntimeError(f"view {body}: {status} {view}")
    return seconds, view


def measure(scene: str, views: int, one_off: int, training: dict) -> dict:
    from harness.cluster import start_api

    job = json.loads((ROOT / "examples" / f"{scene}.json").read_text())
    job.update(iterations=3, images_every=3, training={**job.get("training", {}), **training})
    tmp = Path(tempfile.mkdtemp(prefix="bench-views-api-"))
    env = {"NDRF_STORE": str(tmp / "store"), "NDRF_VIEW_KEEP_SECONDS": "120",   # patient limits: a shared machine
           "NDRF_MAX_PREFLIGHT_SECONDS": "1800", "NDRF_MAX_VIEW_SECONDS": "1800"}
    proc, api = start_api(tmp, env)
    try:
        status, accepted = post(api, "/v1/jobs", job)
        if status != 202:
            raise RuntimeError(f"the job was refused: {status} {accepted}")
        api.wait_status(accepted["id"], {"succeeded"}, 3600)
        path = f"/v1/jobs/{accepted['id']}/views"
        first, view = timed(api, path, {"sensor": 0, "resolution": [128, 128], "spp": 4, "inline": True})
        camera = view["camera"]
        full, preview, render = [], [], []
        for k in range(views):
            seconds, answer = timed(api, path, {**orbit(camera, 0.15 * (k + 1)), "resolution": [64, 64], "spp": 1,
                                                "inline": True})
            preview.append(seconds)
            seconds, answer = timed(api, path, {**orbit(camera, 0.15 * (k + 1)), "resolution": [128, 128], "spp": 4,
                                                "inline": True})
            assert answer["warm"], answer          # the warm child answered
            full.append(seconds)
            render.append(answer["seconds"]["scene"] + answer["seconds"]["fields"])
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    finally:
        proc.kill(signal.SIGKILL)
    proc, api = start_api(tmp, {**env, "NDRF_VIEW_KEEP_SECONDS": "0"})
    try:
        cold = [timed(api, path, {**orbit(camera, -0.2 * (k + 1)), "resolution": [128, 128], "spp": 4,
                                  "inline": True})[0] for k in range(one_off)]
    finally:
        proc.kill(signal.SIGKILL)
        shutil.rmtree(tmp, ignore_errors=True)
    return {"scene": scene, "job": job, "first": first, "warm_128": full, "warm_64": preview,
            "render_128": render, "one_off_128": cold}


def table(result: dict) -> str:
    def row(label, values):
        return [label, len(values), statistics.median(values), min(values), max(values)]

    return markdown_table(["view", "n", "median s", "min s", "max s"], [
        row("first view (starts the job's view child)", [result["first"]]),
        row("warm 128x128, 4 spp", result["warm_128"]),
        row("  of which the render in the child", result["render_128"]),
        row("warm 64x64, 1 spp (preview while dragging)", result["warm_64"]),
        row("one-off child per view, 128x128 (NDRF_VIEW_KEEP_SECONDS=0)", result["one_off_128"])])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.views_api", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", default="hidden-object")
    parser.add_argument("--views", type=int, default=8, help="warm views of each size")
    parser.add_argument("--one-off", type=int, default=3, help="views with a child each")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    result = measure(args.scene, args.views, args.one_off, {"warmup_steps": 200, "residual_points": 2048})
    out = args.out or ROOT / "bench" / "results" / f"views_api-{args.scene}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    note = "a shared 2-core machine (other work ran beside it): upper bounds"
    out.write_text(json.dumps({"machine": machine(), "note": note, **result}, indent=1))
    write_markdown(out, "bench.views_api", argv, f"{note}.\n\n" + table(result))
    log.info("\n%s", table(result))


if __name__ == "__main__":
    main()

"""How long a big mesh's shape job takes to reach its first iteration (#46).

    python -m bench.big_mesh --rings 631

Makes a UV sphere of ``rings x (rings + 2) + 2`` vertices (631: 399,425 vertices, 798,846 faces,
the size of the mesh that once held a worker for 16 minutes without an iteration), writes it as a
PLY beside a one-camera scene, and runs a shape job on it in-process (``sphere.vertex_positions``,
a 16x16 film at 1 spp, 2 iterations, the mesh scaled by 1.1/0.9/1.0 as the synthetic target).
Records the seconds of each preparation phase from ``plan.json`` and the seconds from the start to
iteration 0's record and to the end, and the peak resident memory of the process.
"""

from __future__ import annotations

import argparse
import json
import logging
import resource
import tempfile
import time
from pathlib import Path

from bench.common import machine, markdown_table, write_markdown
from harness.meshes import SPHERE_SCENE, uv_sphere

log = logging.getLogger("bench.big_mesh")
ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "bench" / "results" / "big_mesh.json"

def measure(rings: int) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.solver.scene.shape import ply_bytes

    vertices, faces = uv_sphere(rings)
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        (folder / "sphere.ply").write_bytes(ply_bytes(vertices, faces))
        (folder / "scene.xml").write_text(SPHERE_SCENE)
        job = {"name": "big mesh", "scene": {"path": str(folder / "scene.xml")},
               "parameters": [{"key": "sphere.vertex_positions"}],
               "targets": {"synthetic": {"values": {}, "meshes": {"sphere": {"scale": [1.1, 0.9, 1.0]}}, "spp": 1}},
               "iterations": 2, "render": {"resolution": [16, 16], "spp": 1}}
        first: list[float] = []
        started = time.perf_counter()

        def on_event(event: dict) -> None:
            if event.get("type") == "iteration" and not first:
                first.append(time.perf_counter() - started)

        summary = run_local(JobSpec.model_validate(job), folder / "job", on_event=on_event)
        total = time.perf_counter() - started
        plan = json.loads((folder / "job" / "plan.json").read_text())
    return {"vertices": len(vertices), "faces": len(faces), "scalars": 3 * len(vertices),
            "status": summary["status"], "prepared_seconds": plan["prepared_seconds"],
            "first_iteration_seconds": first[0] if first else None, "total_seconds": total,
            "peak_rss_gib": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rings", type=int, default=631, help="latitude rings of the UV sphere (631: 399,425 "
                                                                "vertices)")
    parser.add_argument("--out", type=Path, default=OUT)
    args = parser.parse_args(argv)
    if args.rings < 2:
        parser.error("--rings must be at least 2")
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    result = {"machine": machine(), **measure(args.rings)}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    phases = result["prepared_seconds"]
    table = markdown_table(
        ["vertices", "faces", "scalars", "status", "load and check s", "targets s", "resolve s",
         "to iteration 0 s", "total s", "peak RSS GiB"],
        [[result["vertices"], result["faces"], result["scalars"], result["status"], phases.get("load"),
          phases.get("targets"), phases.get("resolve"), result["first_iteration_seconds"], result["total_seconds"],
          result["peak_rss_gib"]]])
    write_markdown(args.out, "bench.big_mesh", argv, f"One shape job, in-process.\n\n{table}")
    log.info("wrote %s\n%s", args.out, table)


if __name__ == "__main__":
    main()

"""End-to-end inverse rendering on the hidden-object scene: parameter error against wall time,
per method (the product's own loop, the same job for every method, the same seed)."""

from __future__ import annotations

import json
import logging
import tempfile
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent


def run(quick: bool) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.store.job import JobFiles
    from services.store.local import FolderStore

    base = json.loads((ROOT / "examples" / "hidden-object.json").read_text())
    base.update(images_every=1000, checkpoint_every=1000)
    if quick:
        base.update(iterations=8, render={"spp": 16, "resolution": [32, 32]},
                    training={"warmup_steps": 100, "steps_per_iteration": 4})
    out = {}
    for method in ("ndrf-rhs", "ndrf-lhs", "prb", "radiance-cache", "direct"):
        log.info("end to end: %s", method)
        with tempfile.TemporaryDirectory() as tmp:
            summary = run_local(JobSpec.model_validate(dict(base, method=method)), Path(tmp) / "job")
            files = JobFiles(FolderStore(tmp), "job")
            records = [files.iteration_record(k) for k in files.iterations()]
        elapsed, curve = 0.0, []
        target = np.asarray(summary["target_values"])
        for record in records:
            elapsed += sum(record["seconds"].values())
            error = float(np.max(np.abs(np.asarray(record["updated_parameters"]) - target)))
            curve.append({"iteration": record["iteration"], "seconds": elapsed, "error": error})
        out[method] = {"status": summary["status"], "final": summary["estimate"], "target": summary["target_values"],
                       "curve": curve}
    return out

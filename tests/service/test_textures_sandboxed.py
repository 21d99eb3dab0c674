"""A texture job through the worker's sandboxed child: the textures cross the pipe and land in
the store (final/, iterations/<k>/textures/), and summary.json names them."""

from __future__ import annotations

import threading

import numpy as np

from schemas.job import JobSpec
from schemas.outcomes import Outcome
from schemas.records import JobStatus
from services.jobs.runner import AttemptRunner
from services.jobs.service import JobService
from services.queue.local import LocalEventBus, LocalJobQueue
from services.settings import Limits
from services.store.local import FolderStore
from services.uploads.images import ImageInfo, image_header

KEY = "wall.reflectance.data"


def test_a_texture_job_runs_in_the_sandbox(tmp_path):
    service = JobService(FolderStore(tmp_path / "store"), LocalJobQueue(), LocalEventBus())
    spec = JobSpec.model_validate({"scene": {"builtin": "textured-box"}, "parameters": [{"key": KEY, "init": 0.5}],
                                   "targets": {"synthetic": {"values": {KEY: None}, "spp": 8}}, "iterations": 3,
                                   "render": {"resolution": [16, 16]}, "images_every": 2})
    record, _ = service.submit(spec)
    service.states.transition(record.id, JobStatus.RUNNING, attempt="w#1")
    runner = AttemptRunner(service.states, Limits(), tmp_path / "scratch")
    result = runner.run(record.id, "w#1", lost=threading.Event(), stop=lambda: None)
    assert result.outcome is Outcome.SUCCEEDED, result
    folder = tmp_path / "store" / record.id
    summary = service.states.files(record.id).read("summary.json")
    assert summary["textures"][KEY]["npy"] == f"final/{KEY}.npy"
    assert summary["textures"][KEY]["exr"] == f"final/{KEY}.exr"   # encoded by the host, which has no Mitsuba
    assert image_header((folder / "final" / f"{KEY}.exr").read_bytes()) == ImageInfo("exr", 64, 64, 3)
    assert np.load(folder / "final" / f"{KEY}.npy").shape == (64, 64, 3)
    assert np.load(folder / "final" / f"{KEY}.target.npy").shape == (64, 64, 3)
    assert np.load(folder / "iterations" / "000002" / "textures" / f"{KEY}.dz_dp.npy").shape == (64, 64, 3)

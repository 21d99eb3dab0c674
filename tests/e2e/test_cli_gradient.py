"""``ndrf gradient`` end to end on a small job (fast methods only; the NDRF accuracy is in
test_accuracy.py)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

JOB = {
    "scene": {"builtin": "cornell-box"},
    "parameters": [{"key": "red.reflectance.value", "init": 0.3}],
    "targets": {"synthetic": {"values": {"red.reflectance.value": [0.57, 0.04, 0.04]}, "spp": 64}},
    "render": {"spp": 16, "resolution": [24, 16]},
}


@pytest.fixture()
def job_file(tmp_path):
    path = tmp_path / "job.json"
    path.write_text(json.dumps(JOB))
    return path


@pytest.mark.parametrize("method", ["direct", "prb"])
def test_gradient_command_writes_images_previews_and_summary(mi, job_file, tmp_path, method):
    from cli.main import main

    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["gradient", "--job", str(job_file), "--method", method, "--spp", "8",
                                       "--out", str(out)])
    assert result.exit_code == 0, result.output
    gradients = np.load(out / "gradients.npy")
    assert gradients.shape == (3, 16, 24, 3) and gradients.dtype == np.float32
    assert all((out / f"gradient-{i}.png").is_file() for i in range(3))
    summary = json.loads((out / "summary.json").read_text())
    assert summary["method"] == method and summary["seconds"] > 0 and len(summary["dz_dp"]) == 3
    assert summary["dz_dp"][0] < 0          # the red wall is too dark in red: increasing it lowers the loss
    assert np.abs(gradients[0, ..., 0]).sum() > 0


def test_gradient_command_trains_the_fields_it_needs(mi, job_file, tmp_path):
    from cli.main import main

    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["gradient", "--job", str(job_file), "--method", "ndrf-lhs",
                                       "--train-steps", "3", "--out", str(out)])
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["train_steps"] == 3 and summary["training_seconds"] > 0


def test_bad_job_file_names_the_field_before_rendering(mi, tmp_path):
    from cli.main import main

    bad = dict(JOB, method="magic", render={"spp": 0})
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(bad))
    result = CliRunner().invoke(main, ["gradient", "--job", str(path), "--method", "direct", "--out", str(tmp_path)])
    assert result.exit_code != 0
    assert "method" in result.output and "render.spp" in result.output

"""The API serves a texture job's files: the recovered texture (final/) and a texture and its
gradient at an iteration; names outside the texture pattern are refused. And, as for every job, each
sensor's target as OpenEXR."""

from __future__ import annotations

import io

import numpy as np
from fastapi.testclient import TestClient

from schemas.job import JobSpec
from services.settings import Settings

KEY = "wall.reflectance.data"
JOB = "0123456789abcdef0123"


def _exr_pixels(mi, data: bytes) -> np.ndarray:
    stream = mi.MemoryStream()
    stream.write(data)
    stream.seek(0)
    return np.array(mi.Bitmap(stream, mi.Bitmap.FileFormat.OpenEXR), copy=True)


def test_texture_files_are_served(mi, tmp_path):
    from api.app import create_app
    from services.jobs.local import run_local

    spec = JobSpec.model_validate({"scene": {"builtin": "textured-box"}, "parameters": [{"key": KEY, "init": 0.5}],
                                   "targets": {"synthetic": {"values": {KEY: None}, "spp": 8}}, "iterations": 2,
                                   "render": {"resolution": [16, 16]}, "images_every": 1})
    summary = run_local(spec, tmp_path / "store" / JOB)
    assert summary["status"] == "succeeded"
    with TestClient(create_app(Settings(store=str(tmp_path / "store")))) as client:
        final = client.get(f"/v1/jobs/{JOB}/final/{KEY}.npy")
        assert final.status_code == 200, final.text
        value = np.load(io.BytesIO(final.content))
        assert value.shape == (64, 64, 3)
        assert np.array_equal(value, np.load(tmp_path / "store" / JOB / "final" / f"{KEY}.npy"))
        assert client.get(f"/v1/jobs/{JOB}/final/{KEY}.png").headers["content-type"] == "image/png"
        exr = client.get(f"/v1/jobs/{JOB}/final/{KEY}.exr")
        assert exr.status_code == 200 and exr.headers["content-type"] == "image/x-exr"
        assert exr.content == (tmp_path / "store" / JOB / "final" / f"{KEY}.exr").read_bytes()
        assert np.array_equal(_exr_pixels(mi, exr.content), value)
        gradient = client.get(f"/v1/jobs/{JOB}/iterations/1/textures/{KEY}.dz_dp.npy")
        assert gradient.status_code == 200 and np.load(io.BytesIO(gradient.content)).shape == (64, 64, 3)
        gradient_exr = client.get(f"/v1/jobs/{JOB}/iterations/1/textures/{KEY}.dz_dp.exr")
        assert gradient_exr.headers["content-type"] == "image/x-exr"
        assert np.array_equal(_exr_pixels(mi, gradient_exr.content), np.load(io.BytesIO(gradient.content)))
        assert client.get(f"/v1/jobs/{JOB}/iterations/1/textures/other.npy").status_code == 404
        assert client.get(f"/v1/jobs/{JOB}/final/{KEY}.exe").status_code == 422
        public = client.get(f"/v1/jobs/{JOB}").json()
        assert public["estimate"] is None and public["metrics"]["textures"][KEY]["shape"] == [64, 64, 3]
        assert 0.0 < public["metrics"]["textures"][KEY]["psnr"] < 60.0
        assert client.get(f"/v1/jobs/{JOB}/final/..%2Fspec.json.npy").status_code in (404, 422)
        targets = tmp_path / "store" / JOB / "targets"
        sensors = len(list(targets.glob("target-*.npy")))
        assert sensors == 4                                       # the textured box's views
        for sensor in range(sensors):
            target = client.get(f"/v1/jobs/{JOB}/targets/{sensor}.exr")
            assert target.status_code == 200 and target.headers["content-type"] == "image/x-exr"
            assert np.array_equal(_exr_pixels(mi, target.content), np.load(targets / f"target-{sensor}.npy"))
        assert client.get(f"/v1/jobs/{JOB}/targets/{sensors}.exr").status_code == 404

"""``ndrf run``'s final table, read from the job folder (no rendering): for a texture job the
texture's mean per channel (initial, final, target) and its PSNR against the target; for a shape
job each mesh's file, vertices and Chamfer distance."""

from __future__ import annotations

import json

import numpy as np
from rich.console import Console

from cli.run import _final_table


def test_a_texture_row_shows_means_and_the_psnr_against_the_target(tmp_path):
    target = np.full((4, 4, 3), 0.5, np.float32)
    target[..., 1] = 0.25
    final = target + np.float32(0.01)                       # RMSE 0.01, peak 1: about 40 dB
    (tmp_path / "final").mkdir()
    np.save(tmp_path / "final" / "t.data.npy", final)
    np.save(tmp_path / "final" / "t.data.target.npy", target)
    (tmp_path / "plan.json").write_text(json.dumps(
        {"textures": [{"key": "t.data", "init": {"mean": [0.3, 0.3, 0.3]}}]}))
    summary = {"method": "prb", "status": "succeeded", "iterations": 3, "seconds": 1.0, "scalars": [], "init": [],
               "final": [], "target": None,
               "textures": {"t.data": {"npy": "final/t.data.npy", "target": "final/t.data.target.npy"}}}
    console = Console(width=200, record=True)
    console.print(_final_table(summary, tmp_path))
    text = console.export_text()
    assert "t.data (4x4x3 texture, mean)" in text
    assert "0.300 0.300 0.300" in text                      # initial mean, from the plan
    assert "0.510 0.260 0.510" in text                      # final mean
    assert "0.500 0.250 0.500" in text                      # target mean
    psnr = 10.0 * np.log10(1.0 / float(np.mean((final.astype(np.float64) - target) ** 2)))
    assert f"PSNR {psnr:.2f} dB against the target" in text


def test_a_texture_without_a_target_has_no_psnr(tmp_path):
    (tmp_path / "final").mkdir()
    np.save(tmp_path / "final" / "t.data.npy", np.zeros((2, 2, 1), np.float32))
    summary = {"method": "prb", "status": "succeeded", "iterations": 1, "seconds": 1.0, "scalars": [], "init": [],
               "final": [], "target": None, "textures": {"t.data": {"npy": "final/t.data.npy"}}}
    console = Console(width=200, record=True)
    console.print(_final_table(summary, tmp_path))
    text = console.export_text()
    assert "PSNR" not in text and "final/t.data.npy" in text


def test_a_shape_row_names_the_mesh_file_and_its_chamfer_distance(tmp_path):
    """Failed (an empty table) before meshes had rows."""
    summary = {"method": "direct-projective", "status": "succeeded", "iterations": 40, "seconds": 37.0,
               "scalars": [], "init": [], "final": [], "target": None,
               "meshes": {"sphere": {"vertices": 2414, "faces": 4824, "chamfer": 0.006849, "file": "final/sphere.ply"},
                          "other": {"vertices": 8, "faces": 12, "chamfer": None, "file": "final/other.ply"}}}
    console = Console(width=200, record=True)
    console.print(_final_table(summary, tmp_path))
    text = console.export_text()
    assert "sphere.vertex_positions (2414 vertices)" in text and "Chamfer 0.0068" in text
    assert "sphere: final/sphere.ply, Chamfer distance 0.006849 to the target surface" in text
    assert "other: final/other.ply" in text and "other: final/other.ply," not in text

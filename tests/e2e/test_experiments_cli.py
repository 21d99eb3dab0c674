"""``ndrf experiment`` and ``ndrf compare`` in-process (the embedded runtime in the test's own
process, runs in sandboxed children), and the packing of a local scene for the service."""

from __future__ import annotations

import base64
import csv
import json

import pytest
from click.testing import CliRunner

from client.scenes import SceneError, pack_scene
from harness.cluster import small_job
from tests.support.scenes import QUAD_OBJ, UPLOAD_MATERIALS, UPLOAD_XML


def local_scene(folder):
    (folder / "meshes").mkdir(parents=True)
    (folder / "scene.xml").write_text(UPLOAD_XML)
    (folder / "materials.xml").write_text(UPLOAD_MATERIALS)
    (folder / "meshes" / "quad.obj").write_text(QUAD_OBJ)


def test_a_local_scene_is_packed_with_the_files_it_names(tmp_path):
    local_scene(tmp_path / "scene")
    job = {"scene": {"path": "scene/scene.xml"}, "parameters": []}
    packed = pack_scene({"base": job, "seeds": [1]}, tmp_path)["base"]
    assert packed["scene"]["xml"] == UPLOAD_XML
    assert {k: base64.b64decode(v).decode() for k, v in packed["scene"]["files"].items()} == \
        {"materials.xml": UPLOAD_MATERIALS, "meshes/quad.obj": QUAD_OBJ}
    assert job["scene"] == {"path": "scene/scene.xml"}                     # the input is not changed
    (tmp_path / "scene" / "meshes" / "quad.obj").unlink()
    with pytest.raises(SceneError, match="meshes/quad.obj"):
        pack_scene(job, tmp_path)


def test_experiment_in_process_on_a_local_scene(tmp_path):
    from cli.main import main

    local_scene(tmp_path / "scene")
    base = small_job("direct", iterations=2)
    base.update(scene={"path": "scene/scene.xml"}, render={"spp": 4, "gradient_spp": 4})
    base["parameters"] = [{"key": "paint.reflectance.value", "init": 0.5}]
    base["targets"] = {"synthetic": {"values": {"paint.reflectance.value": [0.3, 0.4, 0.5]}, "spp": 8}}
    spec = tmp_path / "spec.json"
    spec.write_text(json.dumps({"name": "local", "base": base, "grid": {"learning_rate": [0.05, -0.1]}}))
    result = CliRunner().invoke(main, ["experiment", str(spec), "--out", str(tmp_path / "out"), "--quiet"])
    assert result.exit_code == 1 and "runs[1].learning_rate" in result.output        # refused before running

    spec.write_text(json.dumps({"name": "local", "base": base, "grid": {"learning_rate": [0.05, 0.1]}}))
    result = CliRunner().invoke(main, ["experiment", str(spec), "--out", str(tmp_path / "out"), "--jobs", "2",
                                       "--quiet"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader((tmp_path / "out" / "results.csv").open()))
    assert [r["learning_rate"] for r in rows] == ["0.05", "0.1"] and {r["status"] for r in rows} == {"succeeded"}
    assert "local: succeeded, 2 runs" in result.output
    for row in rows:
        assert (tmp_path / "out" / row["job"] / "iterations" / "000001" / "render.png").exists()


@pytest.mark.slow
def test_compare_the_five_methods_on_a_tiny_job(tmp_path):
    from cli.main import main
    from schemas.methods import GEOMETRY_METHODS, Method

    job = small_job("direct", iterations=2)
    job["training"] = dict(job["training"], warmup_steps=4, steps_per_iteration=1)
    path = tmp_path / "job.json"
    path.write_text(json.dumps(job))
    out = tmp_path / "compare"
    result = CliRunner().invoke(main, ["compare", str(path), "--out", str(out), "--jobs", "2", "--seeds", "1",
                                       "--quiet"])
    assert result.exit_code == 0, result.output
    rows = list(csv.DictReader((out / "results.csv").open()))
    five = [m.value for m in Method if m not in GEOMETRY_METHODS]     # the projective two are for geometry
    assert sorted(r["method"] for r in rows) == sorted(five)
    assert {r["status"] for r in rows} == {"succeeded"}
    for method in five:
        assert method in result.output
    svg = (out / "compare.svg").read_text()
    assert svg.startswith("<svg") and svg.count("<polyline") == 10                # 5 methods x (error, loss)
    flat = result.output.replace("\n", "")             # rich wraps long lines to the terminal width
    assert "runs in" in flat and "compare.svg" in flat

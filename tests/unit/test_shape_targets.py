"""Target meshes of another topology (#34): a builtin rounded box or a mesh file as a shape job's
synthetic target, rendered in the shape's place; the upload checks of a target file and the CLI's
packing of it."""

from __future__ import annotations

import base64
import json

import numpy as np
import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.solver.scene.shape import ply_bytes
from services.solver.scene.shaped import icosphere, rounded_box

KEY = "sphere.vertex_positions"
BOX = {"sphere": {"builtin": "rounded-box"}}

#: A tiny XML scene around one PLY mesh, ``blob`` (the shape to optimize), as a user uploads it.
BLOB_XML = """<scene version="3.0.0">
  <integrator type="direct"/>
  <sensor type="perspective">
    <float name="fov" value="35"/>
    <transform name="to_world"><lookat origin="0, 0.7, 2" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
  </sensor>
  <shape type="ply" id="blob"><string name="filename" value="blob.ply"/><bsdf type="diffuse"/></shape>
  <emitter type="constant"><rgb name="radiance" value="0.5, 0.5, 0.5"/></emitter>
</scene>"""
BLOB_FIELD = "targets.synthetic.meshes.blob.file"


def _job(meshes: dict, **overrides) -> dict:
    job = {"scene": {"builtin": "shape-sphere"}, "parameters": [{"key": KEY}],
           "targets": {"synthetic": {"values": {}, "meshes": meshes, "spp": 2}},
           "iterations": 1, "render": {"resolution": [16, 16]}}
    return job | overrides


def _blob_files() -> dict[str, bytes]:
    """``blob.ply``: an icosphere of 162 vertices, radius 0.4; ``target.ply``: a rounded box of
    5 x 5 squares per face (152 vertices), its corners at 0.45."""
    points, faces = icosphere(2)
    box, box_faces = rounded_box(5)
    return {"blob.ply": ply_bytes(points * 0.4, faces), "target.ply": ply_bytes(box * 0.45, box_faces)}


def _blob_job(scene: dict, file: str = "target.ply") -> JobSpec:
    return JobSpec.model_validate({"scene": scene, "parameters": [{"key": "blob.vertex_positions"}],
                                   "targets": {"synthetic": {"values": {}, "meshes": {"blob": {"file": file}},
                                                             "spp": 2}}})


def _uploaded(files: dict[str, bytes]) -> dict:
    return {"xml": BLOB_XML, "files": {name: base64.b64encode(data).decode() for name, data in files.items()}}


def test_target_mesh_sources_in_the_schema():
    """file and builtin exclude each other, builtin names a known mesh, and a target mesh without
    either hashes as before the two fields existed (the hashes computed on main before #34's
    change, recomputed when #43 changed the training defaults, which change the computation and
    so every hash); with one it hashes otherwise."""
    shape_job = _job({"sphere": {"scale": [1.3, 0.8, 1.0], "bump": 0.3}}, iterations=4)
    shape_job["targets"]["synthetic"]["spp"] = 32
    assert JobSpec.model_validate(shape_job).fingerprint() == "2458a23dce02f67a"
    assert JobSpec.model_validate(_job({"sphere": {}}, iterations=4) | {
        "targets": {"synthetic": {"values": {}, "meshes": {"sphere": {}}, "spp": 32}}}).fingerprint() == (
        "48a79014b9988e13")
    boxed = JobSpec.model_validate(_job(BOX))
    assert boxed.targets.synthetic.meshes["sphere"].builtin == "rounded-box"
    assert boxed.fingerprint() != JobSpec.model_validate(_job({"sphere": {}})).fingerprint()
    assert boxed.fingerprint() != JobSpec.model_validate(_job({"sphere": {"file": "box.ply"}})).fingerprint()
    with pytest.raises(ValueError, match="not both"):
        JobSpec.model_validate(_job({"sphere": {"builtin": "rounded-box", "file": "box.ply"}}))
    with pytest.raises(ValueError, match="rounded-box"):
        JobSpec.model_validate(_job({"sphere": {"builtin": "suzanne"}}))
    with pytest.raises(ValueError, match="at least 1 character"):
        JobSpec.model_validate(_job({"sphere": {"file": ""}}))


def test_a_rounded_box_target_renders_in_the_spheres_place(mi):
    """builtin rounded-box on shape-sphere (16x16, 2 spp): the box has its own grid (866
    vertices), its farthest vertex at the sphere's radius about its centre; the shape's span of
    the target values is NaN; every target image is the render of the scene with the box as its
    mesh (the same seeds), smooth-shaded as the sphere is, not the sphere's; afterwards the
    scene's mesh holds exactly what it held before the swap, its faces as loaded."""
    from types import SimpleNamespace

    from services.solver.estimators.render import render
    from services.solver.optimize.setup import prepare
    from services.solver.scene.load import load_scene
    from services.solver.scene.posed import diffuse_mesh
    from services.solver.scene.shaped import shape_sphere_builtin
    from services.solver.seeds import derive_seed

    spec = JobSpec.model_validate(_job(BOX))
    prepared, _ = prepare(spec)
    parameters = prepared.problem.parameters
    mesh = parameters.shapes["sphere"]
    box = mesh.target
    assert box is not None and box.vertices.shape == (866, 3) and box.faces.shape == (1728, 3)
    assert np.linalg.norm(box.vertices - mesh.centre, axis=1).max() == pytest.approx(mesh.radius)
    assert prepared.target_values is not None and np.isnan(prepared.target_values).all()
    assert prepared.textures.error(prepared.init, prepared.target_values) is None   # a shape's error: its Chamfer
    params = parameters.params
    assert np.array_equal(np.asarray(params["sphere.faces"]).reshape(-1, 3), mesh.faces)
    assert np.abs(np.asarray(params[KEY]).reshape(-1, 3) - mesh.v0).max() < 1e-5

    scene = shape_sphere_builtin(16)
    scene["sphere"] = diffuse_mesh("sphere", box.vertices, box.faces, (0.6, 0.6, 0.6), smooth=True)   # as the sphere
    boxed = SimpleNamespace(scene=load_scene(mitsuba_dict=scene, resolution=(16, 16)))
    assert prepared.target_depth is not None
    for sensor, target in prepared.targets.items():
        seed = derive_seed(spec.seed, "target", sensor)
        expected = render(boxed, spp=2, seed=seed, depth=prepared.target_depth, sensor=sensor)   # type: ignore[arg-type]
        sphere = render(prepared.problem, spp=2, seed=seed, depth=prepared.target_depth, sensor=sensor)
        assert np.abs(target - expected).mean() < 1e-4 < 0.01 < np.abs(target - sphere).mean(), sensor

    held = {name: np.asarray(params[f"sphere.{name}"]).copy() for name in ("faces", "vertex_positions", "vertex_normals")}
    with parameters.showing_targets(prepared.target_values):
        assert len(np.asarray(params["sphere.faces"])) == 3 * 1728
    for name, value in held.items():
        assert np.array_equal(np.asarray(params[f"sphere.{name}"]), value), name


def test_a_shape_job_reports_the_chamfer_to_a_target_of_another_topology(mi, tmp_path):
    """One iteration of the rounded-box job, with the sphere's reflectance recovered too (0.6 in
    the scene, 0.5 in the target): the record's Chamfer distance at iteration 0 is the one between
    the sphere and the box (the mesh the step was taken at is the sphere), plan.json says the same,
    and parameter_error is over the reflectance alone (0.1), the shape's NaN target values left
    out. Failed (parameter_error null: NaN, written as null) with the old max over every scalar."""
    from services.jobs.local import run_local
    from services.solver.scene.shape import Surface, chamfer
    from services.solver.scene.shaped import RADIUS

    reflectance = "sphere.bsdf.reflectance.value"
    job = _job(BOX, parameters=[{"key": KEY}, {"key": reflectance}])
    job["targets"]["synthetic"]["values"] = {reflectance: 0.5}
    summary = run_local(JobSpec.model_validate(job), tmp_path / "job")
    assert summary["status"] == "succeeded", summary.get("error")
    record = json.loads(next((tmp_path / "job" / "iterations").glob("*/record.json")).read_text())
    points, faces = icosphere(3)
    box, box_faces = rounded_box()
    expected = chamfer(Surface(points * RADIUS, faces), Surface(box * RADIUS, box_faces))
    assert record["shapes"]["sphere"]["chamfer"] == pytest.approx(expected, rel=1e-3)
    assert record["parameter_error"] == pytest.approx(0.1, abs=1e-6) and record["estimate_error"] is not None
    plan = json.loads((tmp_path / "job" / "plan.json").read_text())
    assert plan["shapes"]["sphere"]["chamfer"] == pytest.approx(expected, rel=1e-3)
    assert plan["target_values"] == pytest.approx([0.5] * 3)


def test_a_file_target_beside_an_xml_scene(mi, tmp_path):
    """A PLY target (a rounded box of 152 vertices) of an uploaded scene is staged with it and read
    by the solver as the shape's target surface, in world space as written; a local XML reads it
    beside the XML file; a path that leaves the folder, a missing file and a built-in scene are
    refused naming the field."""
    from services.solver.optimize.setup import check
    from services.uploads.scene import UploadLimits
    from services.uploads.staging import stage_job

    files = _blob_files()
    box, box_faces = rounded_box(5)
    spec = _blob_job(_uploaded(files))
    scene_file = stage_job(spec, tmp_path / "staged", UploadLimits())
    assert scene_file is not None and (scene_file.parent / "target.ply").is_file()
    target = check(spec, scene_file).parameters.shapes["blob"].target
    assert target is not None and np.array_equal(target.faces, box_faces)
    assert np.abs(target.vertices - box * 0.45).max() < 1e-6

    local = tmp_path / "local"
    (local / "meshes").mkdir(parents=True)
    (local / "scene.xml").write_text(BLOB_XML)
    (local / "blob.ply").write_bytes(files["blob.ply"])
    (local / "meshes" / "box.ply").write_bytes(files["target.ply"])
    (tmp_path / "outside.ply").write_bytes(files["target.ply"])
    target = check(_blob_job({"path": "scene.xml"}, "meshes/box.ply"), local / "scene.xml").parameters.shapes[
        "blob"].target
    assert target is not None and target.vertices.shape == (152, 3)
    for name, why in (("../outside.ply", "leaves the scene's folder"), ("meshes/none.ply", "does not exist")):
        with pytest.raises(InvalidJob, match=why) as refused:
            check(_blob_job({"path": "scene.xml"}, name), local / "scene.xml")
        assert refused.value.field == BLOB_FIELD
    with pytest.raises(InvalidJob, match="built-in scene") as refused:
        check(JobSpec.model_validate(_job({"sphere": {"file": "box.ply"}})))
    assert refused.value.field == "targets.synthetic.meshes.sphere.file"


@pytest.mark.parametrize("case, why", [
    ("missing", "not among the scene's files"),
    ("not a mesh", "not a mesh file"),
    ("broken", "declares 999"),
    ("over the mesh cap", "at most 100 are allowed per mesh"),
    ("over the scene cap", "once the target meshes' 152 vertices"),
    ("built-in scene", "a built-in scene"),
])
def test_an_uploaded_target_file_is_checked_like_a_mesh(tmp_path, case, why):
    """Before a sandboxed child reads it, a target file must be among the scene's files, a PLY or
    OBJ that passes the mesh checks with the service's caps, and its vertices count against the
    scene's cap together with the XML's meshes (162 + 152 here); each refusal names the field."""
    from services.uploads.scene import UploadLimits
    from services.uploads.staging import stage_job

    files, file, limits = _blob_files(), "target.ply", UploadLimits()
    scene: dict = _uploaded(files)
    if case == "missing":
        file = "box.ply"
    elif case == "not a mesh":
        files["target.png"] = b"\x89PNG"
        scene, file = _uploaded(files), "target.png"
    elif case == "broken":
        files["target.ply"] = files["target.ply"].replace(b"element vertex 152", b"element vertex 999")
        scene = _uploaded(files)
    elif case == "over the mesh cap":
        limits = UploadLimits(max_mesh_vertices=100)
    elif case == "over the scene cap":
        limits = UploadLimits(max_scene_vertices=300)
    else:
        scene = {"builtin": "shape-sphere"}
    spec = _blob_job(scene, file)
    with pytest.raises(InvalidJob, match=why) as refused:
        stage_job(spec, tmp_path / "scene", limits)
    field = "scene.files[blob.ply]" if case == "over the scene cap" else BLOB_FIELD
    assert refused.value.field == field
    if case == "over the scene cap":   # the scene alone fits
        stage_job(_blob_job(_uploaded(files), "target.ply"), tmp_path / "scene", UploadLimits(max_scene_vertices=314))


def test_ndrf_submit_packs_the_target_file(tmp_path):
    """The CLI's packing of a local scene sends a job's target mesh file with the XML's files, by
    its path relative to the XML's folder, and refuses one outside the folder."""
    from client.scenes import SceneError, pack_scene

    files = _blob_files()
    (tmp_path / "scene" / "meshes").mkdir(parents=True)
    (tmp_path / "scene" / "scene.xml").write_text(BLOB_XML)
    (tmp_path / "scene" / "blob.ply").write_bytes(files["blob.ply"])
    (tmp_path / "scene" / "meshes" / "box.ply").write_bytes(files["target.ply"])
    job = _blob_job({"path": "scene/scene.xml"}, "./meshes/box.ply").model_dump(mode="json", exclude_none=True)
    packed = pack_scene(job, tmp_path)
    assert sorted(packed["scene"]["files"]) == ["blob.ply", "meshes/box.ply"]
    assert base64.b64decode(packed["scene"]["files"]["meshes/box.ply"]) == files["target.ply"]
    assert packed["targets"]["synthetic"]["meshes"]["blob"]["file"] == "meshes/box.ply"
    assert job["targets"]["synthetic"]["meshes"]["blob"]["file"] == "./meshes/box.ply"    # the caller's, untouched
    JobSpec.model_validate(packed)
    (tmp_path / "outside.ply").write_bytes(files["target.ply"])
    job["targets"]["synthetic"]["meshes"]["blob"]["file"] = "../outside.ply"
    with pytest.raises(SceneError, match="outside the scene's folder"):
        pack_scene(job, tmp_path)

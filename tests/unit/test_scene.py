"""Scene loading (built-in, XML with includes and meshes, dict) and parameter selection."""

from __future__ import annotations

import numpy as np
import pytest

from tests.support.scenes import QUAD_OBJ, SELF_CONTAINED_XML, UPLOAD_MATERIALS, UPLOAD_XML, upload_files


def test_builtin_scenes_load_with_their_parameters(mi):
    from schemas.scenes import BUILTIN_SCENES
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import differentiable_parameters

    expected = {"cornell-box": "red.reflectance.value", "hidden-object": "hidden.reflectance.value",
                "mirror-box": "sphere.reflectance.value"}
    assert set(expected) <= set(BUILTIN_SCENES)
    for name, key in expected.items():
        scene = load_scene(builtin=name)
        keys = [p.key for p in differentiable_parameters(scene.params)]
        assert key in keys, (name, keys)


def test_the_multi_view_rooms_have_eight_cameras_and_differ_by_the_front_wall(mi):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import differentiable_parameters

    closed, opened = load_scene(builtin="room-closed-8"), load_scene(builtin="room-open-8")
    for scene in (closed, opened):
        assert scene.sensor_count == 8 and all(scene.resolution(i) == (128, 128) for i in range(8))
        keys = [p.key for p in differentiable_parameters(scene.params)]
        assert {"walls.reflectance.value", "ball.reflectance.value"} <= set(keys), keys
    assert len(closed.scene.shapes()) == len(opened.scene.shapes()) + 1


def test_closure_is_one_in_a_closed_room_and_less_where_a_wall_is_missing(mi):
    from services.solver.scene.closure import STANDARD_ERROR, closure
    from services.solver.scene.load import load_scene

    closed, opened = load_scene(builtin="room-closed-8"), load_scene(builtin="room-open-8")
    assert closure(closed) == 1.0                       # every ray from a wall hits a wall
    share = closure(opened)
    # one of six equal walls open: a sixth of the walls' rays miss at most; fewer, as walls face each other
    assert share is not None and 1 - 1 / 6 - STANDARD_ERROR < share < 1 - STANDARD_ERROR, share
    assert closure(opened, seed=1) == pytest.approx(share, abs=3 * STANDARD_ERROR)


def test_staged_upload_with_include_and_mesh_relative_to_it(mi, tmp_path):
    from schemas.job import XmlScene
    from services.solver.scene.load import load_scene
    from services.uploads.scene import UploadLimits
    from services.uploads.staging import stage_scene

    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "left-over.xml").write_text("<scene/>")         # staging empties the folder first
    scene_file = stage_scene(XmlScene(xml=UPLOAD_XML, files={k: __import__("base64").b64encode(v).decode()
                                                             for k, v in upload_files().items()}),
                             tmp_path / "scene", UploadLimits())
    assert not (tmp_path / "scene" / "left-over.xml").exists()
    scene = load_scene(xml_path=scene_file)
    assert scene.resolution() == (16, 12)
    assert np.allclose(np.array(scene.params["paint.reflectance.value"]).ravel(), [0.3, 0.4, 0.5])
    assert scene.scene.shapes()[0].surface_area()[0] == pytest.approx(4.0)


def test_a_self_contained_upload_without_files_is_staged_and_loads(mi, tmp_path):
    from schemas.job import XmlScene
    from services.solver.scene.load import load_scene
    from services.uploads.scene import UploadLimits
    from services.uploads.staging import stage_scene

    scene_file = stage_scene(XmlScene(xml=SELF_CONTAINED_XML, files={}), tmp_path / "not-yet-there", UploadLimits())
    assert load_scene(xml_path=scene_file).resolution() == (16, 12)


def test_xml_file_on_disk_and_resolution_override(mi, tmp_path):
    from services.solver.scene.load import load_scene

    (tmp_path / "meshes").mkdir()
    (tmp_path / "materials.xml").write_text(UPLOAD_MATERIALS)
    (tmp_path / "meshes/quad.obj").write_text(QUAD_OBJ)
    (tmp_path / "scene.xml").write_text(UPLOAD_XML)
    scene = load_scene(xml_path=tmp_path / "scene.xml", resolution=(8, 6))
    assert scene.resolution() == (8, 6)
    image = mi.render(scene.scene, spp=1, integrator=mi.load_dict({"type": "path"}))
    assert image.shape[:2] == (6, 8)


def test_parameter_set_flattens_rgb_into_three_scalars(mi):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="cornell-box")
    params = ParameterSet(scene.params, ["red.reflectance.value", "light.emitter.radiance.value"])
    assert params.n == 6
    assert params.labels[0] == "red.reflectance.value[0]"
    values = params.values()
    params.assign(values * 0.5)
    assert np.allclose(params.values(), values * 0.5, rtol=1e-6)
    assert params.owner_kinds() == {"red.reflectance.value": "bsdf", "light.emitter.radiance.value": "emitter"}


@pytest.mark.parametrize("key, reason", [
    ("nope.reflectance.value", "not a key of this scene"),
    ("red-wall.to_world", "not a differentiable material or emitter parameter"),
    ("mirror.specular_reflectance.value", "not a differentiable material or emitter parameter"),
])
def test_parameter_set_refuses_what_would_give_wrong_gradients(mi, key, reason):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="mirror-box")
    with pytest.raises(ValueError, match=reason) as err:
        ParameterSet(scene.params, [key])
    assert "sphere.reflectance.value" in str(err.value)  # the message lists what is allowed


def test_assign_refuses_non_finite_values(mi):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    params = ParameterSet(load_scene(builtin="cornell-box").params, ["red.reflectance.value"])
    with pytest.raises(ValueError, match="non-finite"):
        params.assign(np.array([0.5, np.nan, 0.5]))

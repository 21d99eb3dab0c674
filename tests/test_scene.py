"""Scene loading (built-in, XML with includes and meshes, dict) and parameter selection."""

from __future__ import annotations

import numpy as np
import pytest

OBJ_QUAD = """v -1 0 -1
v 1 0 -1
v 1 0 1
v -1 0 1
f 1 3 2
f 1 4 3
"""

MAIN_XML = """<scene version="3.0.0">
    <include filename="fragments/materials.xml"/>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 3, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
        <film type="hdrfilm"><integer name="width" value="32"/><integer name="height" value="24"/></film>
    </sensor>
    <shape type="obj" id="floor">
        <string name="filename" value="meshes/quad.obj"/>
        <ref id="paint"/>
    </shape>
    <emitter type="constant"><rgb name="radiance" value="1, 1, 1"/></emitter>
</scene>
"""

MATERIALS_XML = """<scene version="3.0.0">
    <bsdf type="diffuse" id="paint"><rgb name="reflectance" value="0.3, 0.4, 0.5"/></bsdf>
</scene>
"""


def test_builtin_scenes_load_with_their_parameters(mi):
    from services.scene.builtin import BUILTIN_SCENES
    from services.scene.load import load_scene
    from services.scene.params import differentiable_parameters

    expected = {"cornell-box": "red.reflectance.value", "hidden-object": "hidden.reflectance.value",
                "mirror-box": "sphere.reflectance.value"}
    assert set(expected) <= set(BUILTIN_SCENES)
    for name, key in expected.items():
        scene = load_scene(builtin=name)
        keys = [p.key for p in differentiable_parameters(scene.params)]
        assert key in keys, (name, keys)


def test_xml_with_include_and_mesh_relative_to_it(mi, tmp_path):
    from services.scene.load import load_scene

    files = {"fragments/materials.xml": MATERIALS_XML.encode(), "meshes/quad.obj": OBJ_QUAD.encode()}
    scene = load_scene(xml=MAIN_XML, files=files, folder=tmp_path)
    assert scene.resolution() == (32, 24)
    assert np.allclose(np.array(scene.params["paint.reflectance.value"]).ravel(), [0.3, 0.4, 0.5])
    assert scene.scene.shapes()[0].surface_area()[0] == pytest.approx(4.0)


def test_xml_file_on_disk_and_resolution_override(mi, tmp_path):
    from services.scene.load import load_scene

    (tmp_path / "fragments").mkdir()
    (tmp_path / "meshes").mkdir()
    (tmp_path / "fragments/materials.xml").write_text(MATERIALS_XML)
    (tmp_path / "meshes/quad.obj").write_text(OBJ_QUAD)
    (tmp_path / "scene.xml").write_text(MAIN_XML)
    scene = load_scene(xml_path=tmp_path / "scene.xml", resolution=(8, 6))
    assert scene.resolution() == (8, 6)
    image = mi.render(scene.scene, spp=1, integrator=mi.load_dict({"type": "path"}))
    assert image.shape[:2] == (6, 8)


def test_parameter_set_flattens_rgb_into_three_scalars(mi):
    from services.scene.load import load_scene
    from services.scene.params import ParameterSet

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
    from services.scene.load import load_scene
    from services.scene.params import ParameterSet

    scene = load_scene(builtin="mirror-box")
    with pytest.raises(ValueError, match=reason) as err:
        ParameterSet(scene.params, [key])
    assert "sphere.reflectance.value" in str(err.value)  # the message lists what is allowed


def test_assign_refuses_non_finite_values(mi):
    from services.scene.load import load_scene
    from services.scene.params import ParameterSet

    params = ParameterSet(load_scene(builtin="cornell-box").params, ["red.reflectance.value"])
    with pytest.raises(ValueError, match="non-finite"):
        params.assign(np.array([0.5, np.nan, 0.5]))

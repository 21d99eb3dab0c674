"""A scene's own ``<default>`` substitutions in file names are resolved before the upload checks
(services.uploads.defaults): what is checked is what is staged and what Mitsuba loads."""

from __future__ import annotations

import base64

import numpy as np
import pytest

from schemas.errors import InvalidJob
from schemas.job import XmlScene
from services.uploads.pack import pack_scene
from services.uploads.scene import UploadLimits
from services.uploads.staging import stage_scene

TEXTURED = """<scene version="3.0.0">
    <default name="tex" value="{value}"/>
    <default name="spp" value="4"/>
    <integrator type="path"/>
    <sensor type="perspective"><film type="hdrfilm"><integer name="width" value="8"/>
        <integer name="height" value="8"/></film>
        <sampler type="independent"><integer name="sample_count" value="$spp"/></sampler></sensor>
    <bsdf type="diffuse" id="wall"><texture type="bitmap" name="reflectance">
        <string name="filename" value="$tex"/></texture></bsdf>
    <shape type="rectangle"><ref id="wall"/></shape>
    <emitter type="constant"/>
</scene>"""


def _png() -> bytes:
    from services.store.images import srgb_png

    return srgb_png(np.full((4, 4, 3), 0.5, np.float32))


def _exr(mi, folder) -> bytes:
    """A float texture (Mitsuba keeps an 8-bit PNG as integers: not differentiable)."""
    mi.Bitmap(np.full((4, 4, 3), 0.5, np.float32)).write(str(folder / "albedo.exr"))
    return (folder / "albedo.exr").read_bytes()


def test_a_default_in_a_file_name_is_resolved_and_staged(mi, tmp_path):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = XmlScene(xml=TEXTURED.format(value="textures/albedo.exr"),
                     files={"textures/albedo.exr": base64.b64encode(_exr(mi, tmp_path)).decode()})
    staged = stage_scene(scene, tmp_path / "scene", UploadLimits())
    assert staged is not None
    text = staged.read_text()
    assert 'value="textures/albedo.exr"' in text and "$tex" not in text
    assert 'name="tex"' not in text and 'name="spp"' in text   # the used-up default is dropped, the other kept
    loaded = load_scene(xml_path=staged)
    assert ParameterSet(loaded.params, ["wall.reflectance.data"]).infos[0].shape == (4, 4, 3)


@pytest.mark.parametrize("value, fragment", [
    ("other.png", "'other.png' is not among the uploaded files"),
    ("../albedo.png", "no '..'"),
    ("/etc/passwd", "no leading '/'"),
])
def test_a_resolved_file_name_gets_every_check(tmp_path, value, fragment):
    scene = XmlScene(xml=TEXTURED.format(value=value), files={"albedo.png": base64.b64encode(_png()).decode()})
    with pytest.raises(InvalidJob, match=fragment):
        stage_scene(scene, tmp_path / "scene", UploadLimits())


def test_ambiguous_and_chained_defaults_are_refused(tmp_path):
    files = {"albedo.png": base64.b64encode(_png()).decode()}
    prefix = TEXTURED.format(value="albedo.png").replace('<default name="spp"', '<default name="texture"')
    with pytest.raises(InvalidJob, match="'tex'> is a prefix of 'texture'"):
        stage_scene(XmlScene(xml=prefix, files=files), tmp_path / "a", UploadLimits())
    chained = TEXTURED.format(value="$spp.png")
    with pytest.raises(InvalidJob, match="must not use another substitution"):
        stage_scene(XmlScene(xml=chained, files=files), tmp_path / "b", UploadLimits())


def test_pack_scene_follows_a_default_file_name(tmp_path):
    (tmp_path / "textures").mkdir()
    (tmp_path / "textures" / "albedo.png").write_bytes(_png())
    (tmp_path / "scene.xml").write_text(TEXTURED.format(value="textures/albedo.png"))
    xml, files = pack_scene(tmp_path / "scene.xml")
    assert list(files) == ["textures/albedo.png"] and "$tex" in xml   # sent as written; the service resolves


def test_an_8_bit_texture_is_refused_with_the_reason(mi, tmp_path):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = XmlScene(xml=TEXTURED.format(value="albedo.png"), files={"albedo.png": base64.b64encode(_png()).decode()})
    loaded = load_scene(xml_path=stage_scene(scene, tmp_path / "scene", UploadLimits()))
    with pytest.raises(ValueError, match="8-bit texture.*float image \\(EXR\\)"):
        ParameterSet(loaded.params, ["wall.reflectance.data"])

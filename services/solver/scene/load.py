"""Load a scene from a built-in name, a Mitsuba XML file (with its includes and meshes), or a
Mitsuba dict.

Scenes are loaded with ``optimize=False``: Mitsuba would otherwise merge shapes that share a BSDF,
and the sampler, `choose_effects` and the tests need per-object identity. Parameter keys are the same
either way.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi

from services.solver.backend import use_mitsuba
from services.solver.scene.builtin import builtin_scene

log = logging.getLogger(__name__)


@dataclass
class LoadedScene:
    """A Mitsuba scene, its ``mi.traverse`` parameters and where it came from."""

    scene: mi.Scene
    params: mi.SceneParameters
    label: str
    folder: Path | None = None

    def sensor(self, index: int = 0) -> mi.Sensor:
        sensors = self.scene.sensors()
        if not 0 <= index < len(sensors):
            raise ValueError(f"sensor {index} does not exist; the scene has {len(sensors)} sensor(s)")
        return sensors[index]

    @property
    def sensor_count(self) -> int:
        return len(self.scene.sensors())

    def resolution(self, index: int = 0) -> tuple[int, int]:
        """``(width, height)`` of the sensor's film."""
        size = self.sensor(index).film().crop_size()
        return int(size[0]), int(size[1])

    def set_resolution(self, width: int, height: int) -> None:
        """Resize the film of every sensor (overriding the scene's own film size)."""
        for sensor in self.scene.sensors():
            film_params = mi.traverse(sensor)
            film_params["film.size"] = mi.ScalarVector2u(width, height)
            film_params.update()


def load_scene(
    *,
    builtin: str | None = None,
    xml_path: str | Path | None = None,
    mitsuba_dict: dict | None = None,
    resolution: tuple[int, int] | None = None,
) -> LoadedScene:
    """Load exactly one of the sources; optionally override the film size ``(width, height)``.

    An XML file is loaded with its includes and meshes resolved relative to it. Uploaded scenes
    reach this function only as files staged by ``services.uploads.staging`` (checked first), and
    only in a sandboxed process.
    """
    sources = [s is not None for s in (builtin, xml_path, mitsuba_dict)]
    if sum(sources) != 1:
        raise ValueError("give exactly one scene source: builtin, xml_path or mitsuba_dict")
    mi_ = use_mitsuba()
    if builtin is not None:
        scene, label, where = mi_.load_dict(builtin_scene(builtin), optimize=False), builtin, None
    elif mitsuba_dict is not None:
        scene, label, where = mi_.load_dict(mitsuba_dict, optimize=False), "dict", None
    else:
        assert xml_path is not None  # exactly one source was checked above
        xml_path = Path(xml_path).resolve()
        if not xml_path.is_file():
            raise FileNotFoundError(f"scene file {xml_path} does not exist")
        scene, label, where = mi_.load_file(str(xml_path), optimize=False), xml_path.name, xml_path.parent
    loaded = LoadedScene(scene, mi_.traverse(scene), label, where)
    if resolution is not None:
        loaded.set_resolution(*resolution)
    log.info("loaded scene %s (%d shapes, %d emitters)", label, len(scene.shapes()), len(scene.emitters()))
    return loaded

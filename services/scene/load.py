"""Load a scene from a built-in name, a Mitsuba XML file (with its includes and meshes), an XML
document plus its uploaded files, or a Mitsuba dict.

Scenes are loaded with ``optimize=False``: Mitsuba would otherwise merge shapes that share a BSDF,
and the sampler, the planner and the tests need per-object identity. Parameter keys are the same
either way.
"""

from __future__ import annotations

import base64
import logging
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import mitsuba as mi

from services.backend import use_mitsuba
from services.scene.builtin import builtin_scene

log = logging.getLogger(__name__)


@dataclass
class LoadedScene:
    """A Mitsuba scene, its ``mi.traverse`` parameters and where it came from."""

    scene: mi.Scene
    params: mi.SceneParameters
    label: str
    folder: Path | None = None
    _keepalive: object = field(default=None, repr=False)

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


def write_scene_files(folder: Path, xml: str, files: Mapping[str, bytes | str]) -> Path:
    """Write an XML document and its files (bytes, or base64 text) under ``folder``.

    Paths must already have been validated (see :mod:`services.scene.sandbox`); this only refuses
    paths that would leave ``folder``, as a last line of defence.
    """
    folder = folder.resolve()
    for rel, data in files.items():
        target = (folder / rel).resolve()
        if folder not in target.parents:
            raise ValueError(f"scene file path {rel!r} leaves the scene folder")
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(base64.b64decode(data, validate=True) if isinstance(data, str) else data)
    main = folder / "scene.xml"
    main.write_text(xml, encoding="utf-8")
    return main


def load_scene(
    *,
    builtin: str | None = None,
    xml_path: str | Path | None = None,
    xml: str | None = None,
    files: Mapping[str, bytes | str] | None = None,
    mitsuba_dict: dict | None = None,
    folder: Path | None = None,
    resolution: tuple[int, int] | None = None,
) -> LoadedScene:
    """Load exactly one of the sources; optionally override the film size ``(width, height)``.

    ``xml`` + ``files`` are written to ``folder`` (a fresh temporary folder when omitted, kept alive
    as long as the returned scene), so that includes and mesh paths resolve relative to the XML.
    """
    sources = [s is not None for s in (builtin, xml_path, xml, mitsuba_dict)]
    if sum(sources) != 1:
        raise ValueError("give exactly one scene source: builtin, xml_path, xml (+ files) or mitsuba_dict")
    mi_ = use_mitsuba()
    keepalive = None
    if builtin is not None:
        scene, label, where = mi_.load_dict(builtin_scene(builtin), optimize=False), builtin, None
    elif mitsuba_dict is not None:
        scene, label, where = mi_.load_dict(mitsuba_dict, optimize=False), "dict", None
    else:
        if xml is not None:
            if folder is None:
                keepalive = tempfile.TemporaryDirectory(prefix="ndrf-scene-")
                folder = Path(keepalive.name)
            xml_path = write_scene_files(folder, xml, files or {})
        xml_path = Path(xml_path).resolve()
        if not xml_path.is_file():
            raise FileNotFoundError(f"scene file {xml_path} does not exist")
        scene, label, where = mi_.load_file(str(xml_path), optimize=False), xml_path.name, xml_path.parent
    loaded = LoadedScene(scene, mi_.traverse(scene), label, where, keepalive)
    if resolution is not None:
        loaded.set_resolution(*resolution)
    log.info("loaded scene %s (%d shapes, %d emitters)", label, len(scene.shapes()), len(scene.emitters()))
    return loaded

"""Cameras no sensor of a job's scene had: a pinhole camera from ``origin``/``target``/``up``/
``fov``, or a scene sensor moved by an offset, and the scene rebuilt with them appended to its
sensors.

Rebuilding keeps every object of the loaded scene (shapes, their BSDFs, emitters, the
integrator): the new scene references the same instances, so parameter keys, values and the
existing sensors' indices are unchanged, and every estimator that takes a sensor index renders the
new cameras as ``sensor_count, sensor_count + 1, ...``. A key that would not survive the rebuild
is a loud error (a gradient image of the wrong object is worse than none).
"""

from __future__ import annotations

import logging

import mitsuba as mi
import numpy as np

from services.solver.scene.load import LoadedScene

log = logging.getLogger(__name__)


def _film(width: int, height: int) -> dict:
    return {"type": "hdrfilm", "width": int(width), "height": int(height), "rfilter": {"type": "box"},
            "pixel_format": "rgb"}


def perspective(origin, target, up, fov: float, width: int, height: int) -> mi.Sensor:
    """A pinhole camera at ``origin`` looking at ``target`` with ``fov`` degrees horizontally and a
    ``width x height`` box-filtered film. Raises ``ValueError`` for a degenerate frame."""
    o, t, u = (np.asarray(v, np.float64).reshape(3) for v in (origin, target, up))
    forward = t - o
    if np.linalg.norm(forward) < 1e-9:
        raise ValueError("origin and target coincide: the camera has no direction")
    scale = float(np.linalg.norm(forward)) * max(float(np.linalg.norm(u)), 1e-30)
    if float(np.linalg.norm(np.cross(forward, u))) < 1e-9 * scale:
        raise ValueError("up is parallel to the viewing direction (target - origin)")
    if not 0.0 < fov < 180.0:
        raise ValueError(f"fov {fov} is outside (0, 180) degrees")
    to_world = mi.ScalarTransform4f().look_at(origin=o.tolist(), target=t.tolist(), up=u.tolist())
    return mi.load_dict({"type": "perspective", "fov": float(fov), "fov_axis": "x", "to_world": to_world,
                         "film": _film(width, height)})


def moved_sensor(loaded: LoadedScene, index: int, offset, width: int | None = None,
                 height: int | None = None) -> mi.Sensor:
    """The scene's sensor ``index`` translated by ``offset`` (world units), with its field of view
    and, unless given, its film size. Only perspective sensors (``x_fov``) can be moved."""
    sensor = loaded.sensor(index)
    values = mi.traverse(sensor)
    if "x_fov" not in values.keys():  # noqa: SIM118 (SceneParameters is not a dict)
        raise ValueError(f"sensor {index} is not a perspective camera: give origin, target, up and fov instead")
    fov = float(np.asarray(values["x_fov"]).reshape(-1)[0])
    w, h = loaded.resolution(index)
    shift = mi.ScalarTransform4f().translate(np.asarray(offset, np.float64).reshape(3).tolist())
    matrix = np.asarray(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    to_world = shift @ mi.ScalarTransform4f(matrix.tolist())
    return mi.load_dict({"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": to_world,
                         "film": _film(width or w, height or h)})


def sensor_pose(loaded: LoadedScene, index: int, offset=(0.0, 0.0, 0.0)) -> dict:
    """The sensor ``index`` (moved by ``offset``) as a free camera: ``origin``, ``target``, ``up``
    (world units, 3 each) and ``fov``. A sensor stores a direction, not a target point: the
    target is the point of its optical axis nearest the scene's bounding-box centre (at least
    1e-3 in front of the camera), the point an orbit viewer turns about."""
    sensor = loaded.sensor(index)
    matrix = np.asarray(sensor.world_transform().matrix, np.float64).reshape(4, 4)
    origin = matrix[:3, 3] + np.asarray(offset, np.float64).reshape(3)
    forward = matrix[:3, 2] / np.linalg.norm(matrix[:3, 2])
    up = matrix[:3, 1] / np.linalg.norm(matrix[:3, 1])
    box = loaded.scene.bbox()
    centre = (np.asarray(box.min, np.float64).reshape(3) + np.asarray(box.max, np.float64).reshape(3)) / 2
    distance = max(float(np.dot(centre - origin, forward)), 1e-3)
    values = mi.traverse(sensor)
    fov = float(np.asarray(values["x_fov"]).reshape(-1)[0]) if "x_fov" in values.keys() else 40.0  # noqa: SIM118
    return {"origin": origin.tolist(), "target": (origin + distance * forward).tolist(), "up": up.tolist(),
            "fov": fov}


def with_cameras(loaded: LoadedScene, cameras: list[mi.Sensor]) -> LoadedScene:
    """The scene of ``loaded`` with ``cameras`` appended to its sensors (the same objects: module
    docstring). Raises ``ValueError`` if a parameter key of the original is missing afterwards."""
    scene = loaded.scene
    entries: dict = {"type": "scene", "integrator": scene.integrator()}
    for i, sensor in enumerate(scene.sensors()):
        entries[sensor.id() or f"sensor-{i}"] = sensor
    # materials before shapes: Mitsuba names a parameter after the first object declaring it
    for shape in scene.shapes():
        bsdf = shape.bsdf()
        if bsdf is not None and bsdf.id():
            entries.setdefault(bsdf.id(), bsdf)
    for i, shape in enumerate(scene.shapes()):
        entries[shape.id() or f"shape-{i}"] = shape
    for i, emitter in enumerate(scene.emitters()):
        if not emitter.flags() & mi.EmitterFlags.Surface:  # area lights come with their shapes
            entries[emitter.id() or f"emitter-{i}"] = emitter
    for i, camera in enumerate(cameras):
        entries[f"view-camera-{i}"] = camera
    rebuilt = mi.load_dict(entries, optimize=False)
    params = mi.traverse(rebuilt)
    missing = sorted(set(loaded.params.keys()) - set(params.keys()))
    if missing:
        raise ValueError(f"rebuilding the scene with new cameras loses parameter(s) {missing[:5]}")
    if len(rebuilt.sensors()) != loaded.sensor_count + len(cameras):
        raise ValueError("rebuilding the scene with new cameras changed its sensors")
    log.info("scene %s rebuilt with %d new camera(s)", loaded.label, len(cameras))
    return LoadedScene(rebuilt, params, loaded.label, loaded.folder)

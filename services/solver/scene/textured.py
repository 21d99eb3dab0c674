"""The textured Cornell box: a bitmap albedo on the back wall (``wall.reflectance.data``).

The built-in ``textured-box`` is Mitsuba's Cornell box without its two blocks (so that every
texel of the back wall is in sight) whose back wall has its own diffuse BSDF with a bitmap
reflectance, the true texture of :func:`true_albedo`, seen by ``views`` cameras from the front at
different heights and sides. :func:`write_textured_box` writes the same scene as Mitsuba XML with
the texture as an EXR file beside it (for a texture size other than the built-in's, and for the
XML path of a job).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from services.solver.backend import use_mitsuba

#: Texels per side of the built-in ``textured-box``'s albedo.
SIZE = 64
#: Cameras of the built-in.
VIEWS = 4
#: Film side of each camera, in pixels.
FILM = 128
#: The parameter key of the back wall's albedo texture.
KEY = "wall.reflectance.data"


def true_albedo(size: int = SIZE) -> np.ndarray:
    """The back wall's true albedo, ``(size, size, 3)`` float32 within [0.1, 0.9]: smooth colour
    ramps with a 4 x 4 checker of +-0.15 on top (sharp edges for the recovery to find)."""
    v, u = np.meshgrid(np.linspace(0.0, 1.0, size), np.linspace(0.0, 1.0, size), indexing="ij")
    checker = np.where((np.floor(u * 4) + np.floor(v * 4)) % 2 == 0, 0.15, -0.15)
    red = 0.25 + 0.5 * u + checker
    green = 0.3 + 0.4 * np.sin(np.pi * v) + 0.5 * checker
    blue = 0.7 - 0.45 * u * v - checker
    return np.clip(np.stack([red, green, blue], axis=-1), 0.1, 0.9).astype(np.float32)


def _sensors(mi, views: int, film: int) -> dict:
    """``views`` cameras at z = 3.9 on a small circle around the box's axis, each looking at the
    back wall's centre (every one sees the whole wall)."""
    T = mi.ScalarTransform4f
    out = {}
    for k in range(views):
        angle = 2.0 * np.pi * (k + 0.5) / views
        origin = [0.6 * float(np.cos(angle)), 0.4 * float(np.sin(angle)), 3.9]
        out[f"sensor-{k}"] = {
            "type": "perspective", "fov": 39.3077, "fov_axis": "smaller",
            "to_world": T().look_at(origin=origin, target=[0.0, 0.0, -1.0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": film, "height": film, "rfilter": {"type": "box"}},
        }
    return out


def textured_box(size: int = SIZE, views: int = VIEWS, film: int = FILM, texture: np.ndarray | None = None,
                 filename: str | None = None) -> dict:
    """The scene as a Mitsuba dict; the albedo is ``texture`` (default :func:`true_albedo`), or
    the file ``filename`` when given (what :func:`write_textured_box` writes)."""
    mi = use_mitsuba()
    box = mi.cornell_box()
    scene = {"type": "scene", "integrator": box["integrator"]}
    scene.update(_sensors(mi, views, film))
    for name in ("white", "green", "red"):
        scene[name] = box[name]
    if filename is not None:
        reflectance = {"type": "bitmap", "filename": filename, "raw": True}
    else:
        data = true_albedo(size) if texture is None else np.asarray(texture, np.float32)
        reflectance = {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True}
    scene["wall"] = {"type": "diffuse", "reflectance": reflectance}
    for name in ("light", "floor", "ceiling", "back", "green-wall", "red-wall"):
        scene[name] = box[name]
    scene["back"] = dict(box["back"], bsdf={"type": "ref", "id": "wall"})
    return scene


def textured_box_builtin() -> dict:
    return textured_box()


#: The built-in ``textured-floor`` (its texture: ``floor-paint.reflectance.data``): texels per side, cameras, film side.
FLOOR_SIZE, FLOOR_VIEWS, FLOOR_FILM = 16, 2, 32


def smooth_albedo(size: int = FLOOR_SIZE) -> np.ndarray:
    """The floor's true albedo, ``(size, size, 3)`` float32 within [0.15, 0.85]: smooth colour ramps
    only (:func:`true_albedo` without its checker; light reflected once carries low frequencies)."""
    v, u = np.meshgrid(np.linspace(0.0, 1.0, size), np.linspace(0.0, 1.0, size), indexing="ij")
    red = 0.2 + 0.6 * u
    green = 0.3 + 0.5 * np.sin(np.pi * v)
    blue = 0.8 - 0.6 * u * v
    return np.clip(np.stack([red, green, blue], axis=-1), 0.15, 0.85).astype(np.float32)


def textured_floor(size: int = FLOOR_SIZE, views: int = FLOOR_VIEWS, film: int = FLOOR_FILM,
                   texture: np.ndarray | None = None) -> dict:
    """The Cornell box without its blocks whose floor has a bitmap albedo (``floor-paint``), seen by
    ``views`` cameras low inside the box looking up at the back wall, the side walls and the
    ceiling: no camera sees the floor, so the texture reaches the images only by the light it
    reflects onto what they see."""
    mi = use_mitsuba()
    box = mi.cornell_box()
    T = mi.ScalarTransform4f
    scene = {"type": "scene", "integrator": box["integrator"]}
    for k in range(views):
        x = 0.5 * (2 * k + 1 - views) / max(views, 1)
        scene[f"sensor-{k}"] = {
            "type": "perspective", "fov": 39.3077, "fov_axis": "smaller",
            "to_world": T().look_at(origin=[x, -0.9, 0.99], target=[-x, 0.1, -1.0], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": film, "height": film, "rfilter": {"type": "box"}},
        }
    for name in ("white", "green", "red"):
        scene[name] = box[name]
    data = smooth_albedo(size) if texture is None else np.asarray(texture, np.float32)
    scene["floor-paint"] = {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True}}
    for name in ("light", "floor", "ceiling", "back", "green-wall", "red-wall"):
        scene[name] = box[name]
    scene["floor"] = dict(box["floor"], bsdf={"type": "ref", "id": "floor-paint"})
    return scene


def textured_floor_builtin() -> dict:
    return textured_floor()


# ------------------------------------------------------------------------------------ XML

_TAGS = {"diffuse": "bsdf", "rectangle": "shape", "cube": "shape", "perspective": "sensor", "path": "integrator",
         "prb": "integrator", "area": "emitter", "hdrfilm": "film", "independent": "sampler", "box": "rfilter",
         "gaussian": "rfilter", "bitmap": "texture", "rgb": "rgb"}


def _xml(name: str | None, value, indent: str, top: bool = False) -> list[str]:
    """XML lines of one entry of a Mitsuba dict (the subset the textured box uses)."""
    mi = use_mitsuba()
    attribute = (f' id="{name}"' if top else f' name="{name}"') if name else ""
    if isinstance(value, dict) and value.get("type") == "rgb":
        return [f'{indent}<rgb{attribute} value="{", ".join(f"{float(c):g}" for c in value["value"])}"/>']
    if isinstance(value, dict) and value.get("type") == "ref":
        return [f'{indent}<ref{attribute if not top else ""} id="{value["id"]}"/>']
    if isinstance(value, dict):
        tag = _TAGS[value["type"]]
        lines = [f'{indent}<{tag} type="{value["type"]}"{attribute}>']
        for key, item in value.items():
            if key != "type":
                lines += _xml(key, item, indent + "    ")
        return lines + [f"{indent}</{tag}>"]
    if isinstance(value, mi.ScalarTransform4f):
        matrix = " ".join(f"{float(x):.9g}" for x in np.asarray(value.matrix, np.float64).reshape(-1))
        return [f'{indent}<transform{attribute}><matrix value="{matrix}"/></transform>']
    if isinstance(value, bool):
        return [f'{indent}<boolean{attribute} value="{str(value).lower()}"/>']
    if isinstance(value, int):
        return [f'{indent}<integer{attribute} value="{value}"/>']
    if isinstance(value, float):
        return [f'{indent}<float{attribute} value="{value:.9g}"/>']
    if isinstance(value, str):
        return [f'{indent}<string{attribute} value="{value}"/>']
    raise TypeError(f"cannot write {name}={value!r} as Mitsuba XML")


def write_textured_box(folder: Path, size: int = SIZE, views: int = VIEWS, film: int = FILM,
                       texture: np.ndarray | None = None) -> Path:
    """Write ``scene.xml`` and ``albedo.exr`` (the texture, default :func:`true_albedo`) into
    ``folder``; returns the XML's path."""
    mi = use_mitsuba()
    folder.mkdir(parents=True, exist_ok=True)
    data = true_albedo(size) if texture is None else np.asarray(texture, np.float32)
    mi.Bitmap(data).write(str(folder / "albedo.exr"))
    scene = textured_box(size, views, film, filename="albedo.exr")
    lines = ['<scene version="3.0.0">']
    for key, value in scene.items():
        if key != "type":
            lines += _xml(key, value, "    ", top=True)
    path = folder / "scene.xml"
    path.write_text("\n".join(lines + ["</scene>", ""]))
    return path

"""Built-in scenes, as Mitsuba dictionaries.

Each factory returns a fresh dict (Mitsuba mutates nothing, but callers may). Materials are
declared at the top level and referenced by the shapes, so parameter keys read as
``<material>.<property>.value`` (for example ``red.reflectance.value``).

``cornell-box``     Mitsuba's own ``mi.cornell_box()``.
``hidden-object``   A closed room; a diffuse sphere (``hidden.reflectance.value``) sits behind the
                    camera, under the only light, and reaches the image only through
                    interreflection (the setting of the paper's Fig. 5).
``mirror-box``      The Cornell box with a perfect mirror as back wall and a diffuse sphere
                    (``sphere.reflectance.value``) seen directly and in the mirror.
``glossy-box``      The Cornell box with a rough gold sphere (GGX, ``metal.alpha.value`` = 0.15):
                    glossy reflections of the walls, and a roughness to optimize.
``closet-box``      The Cornell box with a closed cube hiding a sphere: its parameters cannot change
                    the image (`choose_effects` drops them).
``room-closed-8``   The ``hidden-object`` room with a sphere in sight (``ball.reflectance.value``) and
                    8 cameras of 128x128 around it: a multi-view job with long light paths.
``room-open-8``     The same room without its front wall: light escapes, paths are shorter.
``textured-box``    The Cornell box without its blocks, a 64 x 64 albedo texture on the back wall
                    (``wall.reflectance.data``), 4 cameras (:mod:`.textured`).
``textured-floor``  The same box whose floor has a 16 x 16 albedo texture
                    (``floor-paint.reflectance.data``), hidden from its 2 cameras: the texture
                    acts through the light it reflects onto the walls (:mod:`.textured`).
``pose-block``      A generated block on a floor under an area light, 2 cameras: its pose is a
                    geometry parameter (:mod:`.posed`).
``shape-sphere``    A generated icosphere under a constant sky and an area light, 6 cameras: its
                    vertices are a shape parameter (:mod:`.shaped`).
"""

from __future__ import annotations

import math
from collections.abc import Callable

from schemas.scenes import BUILTIN_SCENES
from services.solver.backend import use_mitsuba
from services.solver.scene.posed import pose_block_builtin
from services.solver.scene.shaped import shape_sphere_builtin
from services.solver.scene.textured import textured_box_builtin, textured_floor_builtin


def _diffuse(rgb) -> dict:
    return {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(rgb)}}


def cornell_box() -> dict:
    mi = use_mitsuba()
    return mi.cornell_box()


def _room(mi, open_front: bool = False) -> dict:
    """The walls (``walls.reflectance.value``) and ceiling light of the rooms: x and y in [-1, 1],
    z in [-1, 1.5]; without the front wall (z = 1.5) if ``open_front``."""
    T = mi.ScalarTransform4f
    grey = {"type": "ref", "id": "walls"}
    depth = 1.25
    room = {
        "floor": {"type": "rectangle", "bsdf": grey,
                  "to_world": T().translate([0, -1, 0.25]).rotate([1, 0, 0], -90).scale([1, depth, 1])},
        "ceiling": {"type": "rectangle", "bsdf": grey,
                    "to_world": T().translate([0, 1, 0.25]).rotate([1, 0, 0], 90).scale([1, depth, 1])},
        "back": {"type": "rectangle", "bsdf": grey, "to_world": T().translate([0, 0, -1])},
        "front": {"type": "rectangle", "bsdf": grey,
                  "to_world": T().translate([0, 0, 1.5]).rotate([0, 1, 0], 180)},
        "left": {"type": "rectangle", "bsdf": grey,
                 "to_world": T().translate([-1, 0, 0.25]).rotate([0, 1, 0], 90).scale([depth, 1, 1])},
        "right": {"type": "rectangle", "bsdf": grey,
                  "to_world": T().translate([1, 0, 0.25]).rotate([0, 1, 0], -90).scale([depth, 1, 1])},
        "light": {
            "type": "rectangle",
            "to_world": T().translate([0, 0.99, 0.95]).rotate([1, 0, 0], 90).scale(0.25),
            "bsdf": grey,
            "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [40.0, 40.0, 40.0]}},
        },
    }
    if open_front:
        del room["front"]
    return room


def hidden_object() -> dict:
    mi = use_mitsuba()
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 12},
        "sensor": {  # the camera looks down -z from z = 0.7: the sphere at z = 1.05 is behind it
            "type": "perspective",
            "fov": 70.0,
            "to_world": T().look_at(origin=[0, 0.1, 0.7], target=[0, -0.1, -1], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 64, "height": 64, "rfilter": {"type": "box"}},
        },
        "walls": _diffuse([0.5, 0.5, 0.5]),
        "hidden": _diffuse([0.8, 0.35, 0.1]),
        **_room(mi),
        "hidden-sphere": {"type": "sphere", "center": [0, -0.55, 1.05], "radius": 0.4,
                          "bsdf": {"type": "ref", "id": "hidden"}},
    }


def _multi_view_room(open_front: bool, views: int = 8) -> dict:
    """The room of ``hidden-object`` with a sphere in sight (``ball.reflectance.value``) and
    ``views`` cameras (128x128) on an ellipse around it, each looking across the room past the
    sphere, so every view sees walls, floor or ceiling and the sphere from another side."""
    mi = use_mitsuba()
    T = mi.ScalarTransform4f
    scene: dict = {"type": "scene", "integrator": {"type": "path", "max_depth": 12},
                   "walls": _diffuse([0.5, 0.5, 0.5]), "ball": _diffuse([0.8, 0.2, 0.1])}
    for k in range(views):
        angle = 2 * math.pi * (k + 0.5) / views
        c, s = math.cos(angle), math.sin(angle)
        scene[f"sensor-{k}"] = {
            "type": "perspective", "fov": 75.0,
            "to_world": T().look_at(origin=[0.8 * c, 0.35, 0.25 + 1.05 * s],
                                    target=[-0.35 * c, -0.55, 0.25 - 0.45 * s], up=[0, 1, 0]),
            "film": {"type": "hdrfilm", "width": 128, "height": 128, "rfilter": {"type": "box"}},
        }
    scene.update(_room(mi, open_front=open_front))
    scene["ball-sphere"] = {"type": "sphere", "center": [0, -0.6, 0.25], "radius": 0.4,
                            "bsdf": {"type": "ref", "id": "ball"}}
    return scene


def room_closed_8() -> dict:
    return _multi_view_room(open_front=False)


def room_open_8() -> dict:
    return _multi_view_room(open_front=True)


def mirror_box() -> dict:
    box = cornell_box()
    # Materials first: Mitsuba names a parameter after the first object that declares it.
    first = ("type", "integrator", "sensor", "white", "green", "red")
    d = {k: box[k] for k in first}
    d["mirror"] = {"type": "conductor", "material": "none"}
    d["sphere"] = _diffuse([0.2, 0.3, 0.8])
    d.update({k: v for k, v in box.items() if k not in d})
    d["back"]["bsdf"] = {"type": "ref", "id": "mirror"}
    d["blue-sphere"] = {"type": "sphere", "center": [0.35, -0.55, -0.2], "radius": 0.3,
                        "bsdf": {"type": "ref", "id": "sphere"}}
    return d


def glossy_box() -> dict:
    d = cornell_box()
    d["metal"] = {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.15}
    d["gold-sphere"] = {"type": "sphere", "center": [-0.35, -0.62, 0.35], "radius": 0.38,
                        "bsdf": {"type": "ref", "id": "metal"}}
    return d


def closet_box() -> dict:
    """The Cornell box plus a closed cube (the closet) hiding a sphere with its own material
    (``hidden-paint.reflectance.value``): no light and no camera path reaches the sphere."""
    mi = use_mitsuba()
    T = mi.ScalarTransform4f
    d = cornell_box()
    d["hidden-paint"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0.1, 0.1]}}
    d["closet"] = {"type": "cube", "to_world": T().translate([0.55, 0.55, -0.55]).scale(0.3),
                   "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}}
    d["treasure"] = {"type": "sphere", "center": [0.55, 0.55, -0.55], "radius": 0.1,
                     "bsdf": {"type": "ref", "id": "hidden-paint"}}
    return d


#: Factories by name; the names and descriptions clients see are :data:`schemas.scenes.BUILTIN_SCENES`.
FACTORIES: dict[str, Callable[[], dict]] = {
    "cornell-box": cornell_box,
    "hidden-object": hidden_object,
    "mirror-box": mirror_box,
    "glossy-box": glossy_box,
    "closet-box": closet_box,
    "room-closed-8": room_closed_8,
    "room-open-8": room_open_8,
    "textured-box": textured_box_builtin,
    "textured-floor": textured_floor_builtin,
    "pose-block": pose_block_builtin,
    "shape-sphere": shape_sphere_builtin,
}
if set(FACTORIES) != set(BUILTIN_SCENES):  # the catalogue and the factories must name the same scenes
    raise ImportError(f"built-in scenes differ: {sorted(set(FACTORIES) ^ set(BUILTIN_SCENES))}")


def builtin_scene(name: str) -> dict:
    """The Mitsuba dict of built-in scene ``name``; a ``KeyError`` lists the known names."""
    try:
        factory = FACTORIES[name]
    except KeyError:
        raise KeyError(f"unknown built-in scene {name!r}; known: {', '.join(sorted(FACTORIES))}") from None
    return factory()

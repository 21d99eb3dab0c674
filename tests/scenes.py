"""Small scenes built by the tests (the product's tests never read ../shared)."""

from __future__ import annotations


def _t():
    from services.backend import use_mitsuba

    return use_mitsuba().ScalarTransform4f


def sky_plane(albedo=(0.5, 0.5, 0.5), sky=1.0) -> dict:
    """A diffuse square (y = 0, facing +y) under a constant white sky of radiance ``sky``.

    Nothing else: the reflected radiance everywhere on the square is exactly ``albedo · sky``,
    and its derivative w.r.t. the albedo is ``sky`` (per channel).
    """
    T = _t()
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 45,
                   "to_world": T().look_at(origin=[0, 3, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "plane-bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": list(albedo)}},
        "plane": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90), "bsdf": {"type": "ref", "id": "plane-bsdf"}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": [sky, sky, sky]}},
    }


def area_probe() -> dict:
    """Shapes of known area and height for the area-sampling test: a floor (2x2 at y = -1), a
    sphere (r = 0.25 at y = 0.5), plus an emitter and a mirror that must be excluded."""
    T = _t()
    return {
        "type": "scene",
        "floor": {"type": "rectangle", "to_world": T().translate([0, -1, 0]).rotate([1, 0, 0], -90),
                  "bsdf": {"type": "diffuse"}},
        "ball": {"type": "sphere", "center": [0, 0.5, 0], "radius": 0.25, "bsdf": {"type": "diffuse"}},
        "light": {"type": "rectangle", "to_world": T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(0.3),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [5, 5, 5]}}},
        "mirror": {"type": "rectangle", "to_world": T().translate([0, 0, -2]),
                   "bsdf": {"type": "conductor", "material": "none"}},
    }


def closet_box() -> dict:
    """The Cornell box plus a closed cube (the closet) hiding a sphere with its own material: no
    light and no camera path reaches the sphere, so its parameters cannot change the image."""
    from services.scene.builtin import cornell_box

    T = _t()
    d = cornell_box()
    d["hidden-paint"] = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.9, 0.1, 0.1]}}
    d["closet"] = {"type": "cube", "to_world": T().translate([0.55, 0.55, -0.55]).scale(0.3),
                   "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}}
    d["treasure"] = {"type": "sphere", "center": [0.55, 0.55, -0.55], "radius": 0.1,
                     "bsdf": {"type": "ref", "id": "hidden-paint"}}
    return d

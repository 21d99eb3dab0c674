"""Hard cases for numerical stability, built by the tests (small, fast): each returns a Mitsuba
dict; the tests register them as built-in scenes for the duration of a test."""

from __future__ import annotations


def _t():
    from services.solver.backend import use_mitsuba

    return use_mitsuba().ScalarTransform4f


def _box():
    from services.solver.scene.builtin import cornell_box

    return cornell_box()


def rough_metal(alpha: float) -> dict:
    """Cornell box with a rough conductor sphere of roughness ``alpha`` (a near-specular lobe for
    alpha = 0.001): the optimized parameter is the roughness itself."""
    d = _box()
    d["metal"] = {"type": "roughconductor", "material": "Au", "alpha": alpha, "distribution": "ggx"}
    d["ball"] = {"type": "sphere", "center": [0.3, -0.6, 0.2], "radius": 0.35, "bsdf": {"type": "ref", "id": "metal"}}
    return d


def glass() -> dict:
    """Cornell box with a smooth glass sphere in front of the red wall (delta transmission, total
    internal reflection): the red wall is partly seen through it."""
    d = _box()
    d["glass-ball"] = {"type": "sphere", "center": [-0.45, -0.3, 0.3], "radius": 0.35,
                       "bsdf": {"type": "dielectric", "int_ior": 1.5}}
    return d


def grazing() -> dict:
    """A diffuse floor seen at 87 degrees from its normal, lit by an area light."""
    import math

    T = _t()
    angle = math.radians(87.0)
    eye = [0.0, 2.0 * math.cos(angle), 2.0 * math.sin(angle)]
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30, "to_world": T().look_at(origin=eye, target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 16, "rfilter": {"type": "box"}}},
        "paint": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(3),
                  "bsdf": {"type": "ref", "id": "paint"}},
        "light": {"type": "rectangle", "to_world": T().translate([0, 2, 0]).rotate([1, 0, 0], 90).scale(0.5),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [10, 10, 10]}}},
    }


def tiny_bright_light() -> dict:
    """The Cornell box lit by a 2 cm light of radiance 1e4 (the same power as a dim large one)."""
    d = _box()
    d["light"]["to_world"] = _t().translate([0, 0.99, 0.01]).rotate([1, 0, 0], 90).scale(0.01)
    d["light"]["emitter"]["radiance"]["value"] = [1e4, 1e4, 1e4]
    return d


def scaled(factor: float) -> dict:
    """The Cornell box with every length multiplied by ``factor`` (the image is the same)."""
    T = _t()
    d = _box()
    scale = T().scale(factor)
    for key, value in d.items():
        if isinstance(value, dict) and "to_world" in value and key != "sensor":
            value["to_world"] = scale @ value["to_world"]
    # a camera transform must stay rigid: move the eye, do not scale the frame
    d["sensor"]["to_world"] = T().look_at(origin=[0, 0, 3.9 * factor], target=[0, 0, 0], up=[0, 1, 0])
    d["sensor"]["near_clip"] = d["sensor"]["near_clip"] * factor
    d["sensor"]["far_clip"] = d["sensor"]["far_clip"] * factor
    return d

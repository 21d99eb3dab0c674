"""Small scenes built by the tests (the product's tests never read ../shared), in one place."""

from __future__ import annotations


def _t():
    from services.solver.backend import use_mitsuba

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


# An uploaded scene: an include and a mesh in a sub-folder, so paths must resolve relative to the XML.
UPLOAD_XML = """<scene version="3.0.0">
  <include filename="materials.xml"/>
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 3, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/></film>
  </sensor>
  <shape type="obj"><string name="filename" value="meshes/quad.obj"/><ref id="paint"/></shape>
  <emitter type="constant"><rgb name="radiance" value="1, 1, 1"/></emitter>
</scene>"""
UPLOAD_MATERIALS = ('<scene version="3.0.0"><bsdf type="diffuse" id="paint">'
                    '<rgb name="reflectance" value="0.3, 0.4, 0.5"/></bsdf></scene>')
QUAD_OBJ = "v -1 0 -1\nv 1 0 -1\nv 1 0 1\nv -1 0 1\nf 1 3 2\nf 1 4 3\n"
#: A self-contained XML (no files at all: the simplest upload there is).
SELF_CONTAINED_XML = """<scene version="3.0.0">
  <sensor type="perspective">
    <transform name="to_world"><lookat origin="0, 3, 3" target="0, 0, 0" up="0, 1, 0"/></transform>
    <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="12"/></film>
  </sensor>
  <bsdf type="diffuse" id="paint"><rgb name="reflectance" value="0.3, 0.4, 0.5"/></bsdf>
  <shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/></transform><ref id="paint"/></shape>
  <emitter type="constant"><rgb name="radiance" value="1, 1, 1"/></emitter>
</scene>"""


def upload_files() -> dict[str, bytes]:
    return {"materials.xml": UPLOAD_MATERIALS.encode(), "meshes/quad.obj": QUAD_OBJ.encode()}


def upload_scene(xml: str = UPLOAD_XML, files: dict[str, bytes] | None = None) -> dict:
    """The job file's ``scene`` of the uploaded scene (files as base64)."""
    import base64

    files = upload_files() if files is None else files
    return {"xml": xml, "files": {path: base64.b64encode(data).decode() for path, data in files.items()}}


def poster_box(height: int = 2, width: int = 3) -> dict:
    """The Cornell box whose back wall is a grey bitmap of ``height x width`` texels (nearest
    filter): a parameter (``back.bsdf.reflectance.data``) that is a texture, not a value."""
    import numpy as np

    from services.solver.backend import use_mitsuba
    from services.solver.scene.builtin import cornell_box

    mi = use_mitsuba()
    d = cornell_box()
    texels = np.full((height, width, 1), 0.7, dtype=np.float32)
    d["poster"] = {"type": "diffuse", "reflectance": {"type": "bitmap", "bitmap": mi.Bitmap(texels), "raw": True,
                                                      "filter_type": "nearest"}}
    d["back"]["bsdf"] = {"type": "ref", "id": "poster"}
    return d

"""``pose-block``: a built-in scene for geometry, a block on a floor under an area light.

The block (``block``) is a mesh the project generates (no file): a box of 0.5 x 0.25 x 0.3 scene
units whose 8 corners are shared by its 12 triangles. Shared vertices matter for Mitsuba's
projective integrators: they find silhouette edges between adjacent triangles, and a mesh whose
faces each own their vertices (Mitsuba's ``cube``) has only open edges, every one of them taken
for a silhouette (measured: translation gradients about twice the finite differences on the
``cube``, within 10% on this block; ``tests/unit/test_geometry.py``). Its pose,
``block.to_world.translate`` and ``block.to_world.rotate``, is what a pose job recovers. Two
cameras of 32x32 look at it from the front and from the side.
"""

from __future__ import annotations

import numpy as np

from services.solver.backend import use_mitsuba

#: The block's half extents and the centre of its bounding box (scene units).
HALF = np.array([0.25, 0.125, 0.15])
CENTRE = np.array([0.0, 0.125, 0.0])
#: The box's 12 triangles over its corners ``(x, y, z)`` in {-1, 1}^3, index ``4 x + 2 y + z``
#: (bits), wound outwards.
FACES = np.array([[0, 1, 3], [0, 3, 2], [4, 6, 7], [4, 7, 5], [0, 4, 5], [0, 5, 1],
                  [2, 3, 7], [2, 7, 6], [0, 2, 6], [0, 6, 4], [1, 5, 7], [1, 7, 3]], np.uint32)


def diffuse_mesh(name: str, vertices: np.ndarray, faces: np.ndarray, reflectance, smooth: bool = False):
    """A generated mesh, ``vertices`` ``(N, 3)`` and ``faces`` ``(F, 3)``, as a Mitsuba mesh with a
    diffuse BSDF of ``reflectance`` (the built-in scenes' blocks and spheres). ``smooth``: with
    vertex normals (a smooth surface's mesh; Mitsuba recomputes them whenever the vertices move),
    else flat-shaded, each triangle its own normal (a box's faces)."""
    mi = use_mitsuba()
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": list(reflectance)}})
    mesh = mi.Mesh(name, len(vertices), len(faces), props, smooth, False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.asarray(vertices).ravel().astype(np.float32))
    params["faces"] = mi.UInt32(np.asarray(faces).ravel().astype(np.uint32))
    params.update()
    if smooth:
        mesh.recompute_vertex_normals()
    return mesh


def block_mesh(name: str = "block", reflectance=(0.7, 0.3, 0.2)):
    """The block as a Mitsuba mesh with a diffuse BSDF of ``reflectance``."""
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], np.float64)
    return diffuse_mesh(name, corners * HALF + CENTRE, FACES, reflectance)


def pose_block_builtin(resolution: int = 32) -> dict:
    """The scene (module docstring)."""
    mi = use_mitsuba()
    T = mi.ScalarTransform4f

    def camera(origin) -> dict:
        return {"type": "perspective", "fov": 35, "to_world": T().look_at(origin=origin, target=[0, 0.12, 0],
                                                                         up=[0, 1, 0]),
                "film": {"type": "hdrfilm", "width": resolution, "height": resolution,
                         "rfilter": {"type": "box"}, "sample_border": True},
                "sampler": {"type": "independent", "sample_count": 16}}

    return {
        "type": "scene",
        "integrator": {"type": "path"},
        "front": camera([0.4, 0.9, 1.8]),
        "side": camera([1.8, 0.9, -0.3]),
        "floor": {"type": "rectangle", "to_world": T().rotate([1, 0, 0], -90).scale(2.0),
                  "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}}},
        "block": block_mesh(),
        "light": {"type": "rectangle", "to_world": T().look_at(origin=[0.3, 2.0, 0.5], target=[0, 0, 0],
                                                            up=[0, 0, 1]).scale(0.4),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": [20.0, 20.0, 20.0]}}},
    }

"""Geometry parameters: a mesh's pose, moved on top of the scene file's own ``to_world``.

A job names a shape's pose by two keys that are not ``mi.traverse`` keys (Mitsuba keeps a mesh's
vertices in world space, with the file's ``to_world`` already applied):

``<shape id>.to_world.translate``  3 scalars, ``t``, in scene units
``<shape id>.to_world.rotate``     3 Euler angles in degrees, ``(a_x, a_y, a_z)``: about x, then
                                   y, then z, so ``R = R_z(a_z) R_y(a_y) R_x(a_x)``

Both move the vertices as loaded, ``v_0``, about the centre ``c`` of their bounding box (what
Mitsuba's pose tutorial does to the bunny's ``vertex_positions``)::

    v = R (v_0 - c) + c + t            (every vertex; (N, 3) in world space)

so the shape's new ``to_world`` is ``D · M`` with ``M`` the file's own and the pose's matrix
``D = T(c + t) · R · T(-c)`` (:func:`pose_matrix`). The vertices are computed in Dr.Jit from the
pose's scalars, so the gradient of a render reaches them through Mitsuba's projective integrators
(``prb-projective``, ``direct-projective``), which differentiate the moving silhouettes.

A pose is reported as ``D`` (4x4, row-major) and as the Mitsuba XML ``<transform>`` a user pastes
back into the shape (:func:`transform_xml`): its operations come after the file's own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

TRANSLATE, ROTATE = "to_world.translate", "to_world.rotate"
#: The geometry keys' suffixes and the scalars each holds.
POSE_KEYS = {TRANSLATE: 3, ROTATE: 3}


def split_key(key: str) -> tuple[str, str] | None:
    """``(shape id, kind)`` of a geometry key (``kind`` one of :data:`POSE_KEYS`), else None."""
    for kind in POSE_KEYS:
        if key.endswith("." + kind) and len(key) > len(kind) + 1:
            return key[: -len(kind) - 1], kind
    return None


def mesh_shapes(params: mi.SceneParameters) -> list[str]:
    """The ids of the scene's meshes whose vertices may move (those with ``vertex_positions``)."""
    suffix = ".vertex_positions"
    return [key[: -len(suffix)] for key in params.keys() if key.endswith(suffix)]  # noqa: SIM118


def geometry_keys(params: mi.SceneParameters) -> list[str]:
    """Every pose key of the scene's meshes, as listed to users."""
    return [f"{shape}.{kind}" for shape in mesh_shapes(params) for kind in POSE_KEYS]


def rotation_matrix(angles: np.ndarray) -> np.ndarray:
    """``R = R_z R_y R_x`` of Euler angles in degrees, ``(3, 3)`` float64."""
    ax, ay, az = np.radians(np.asarray(angles, np.float64).reshape(3))
    cx, sx, cy, sy, cz, sz = math.cos(ax), math.sin(ax), math.cos(ay), math.sin(ay), math.cos(az), math.sin(az)
    rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return rz @ ry @ rx


def pose_matrix(translate: np.ndarray, rotate: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """``D = T(c + t) · R · T(-c)``, ``(4, 4)`` float64 (module docstring)."""
    rotation = rotation_matrix(rotate)
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = np.asarray(centre) + np.asarray(translate) - rotation @ np.asarray(centre)
    return out


def transform_xml(translate: np.ndarray, rotate: np.ndarray, centre: np.ndarray, indent: str = "    ") -> str:
    """The pose as the operations of a Mitsuba XML ``<transform name="to_world">``: pasted after
    the shape's own operations (each later operation applies after the earlier ones), they give
    the recovered ``to_world``; for a shape without one, the element is the whole answer."""
    c, t, a = (np.asarray(v, np.float64).reshape(3) for v in (centre, translate, rotate))

    def vec(v: np.ndarray) -> str:
        return ", ".join(f"{x:.9g}" for x in v)

    lines = ['<transform name="to_world">',
             f"{indent}<!-- the shape's own to_world operations from the scene file, if any, go here -->",
             f'{indent}<translate value="{vec(-c)}"/>',
             f'{indent}<rotate x="1" angle="{a[0]:.9g}"/>',
             f'{indent}<rotate y="1" angle="{a[1]:.9g}"/>',
             f'{indent}<rotate z="1" angle="{a[2]:.9g}"/>',
             f'{indent}<translate value="{vec(c + t)}"/>',
             "</transform>"]
    return "\n".join(lines)


def _rotation_dr(angles) -> list[list]:
    """``R_z R_y R_x`` of a Dr.Jit ``Float`` of 3 angles in degrees: 3 x 3 nested Floats (attached)."""
    ax, ay, az = (dr.gather(mi.Float, angles, i) * (math.pi / 180.0) for i in range(3))
    cx, sx, cy, sy, cz, sz = dr.cos(ax), dr.sin(ax), dr.cos(ay), dr.sin(ay), dr.cos(az), dr.sin(az)
    return [[cz * cy, cz * sy * sx - sz * cx, cz * sy * cx + sz * sx],
            [sz * cy, sz * sy * sx + cz * cx, sz * sy * cx - cz * sx],
            [-sy, cy * sx, cy * cx]]


@dataclass
class ShapePose:
    """One mesh whose pose is optimized: its vertices as loaded ``v0`` ``(N, 3)``, its faces ``(F,
    3)``, the centre of its bounding box, and the current pose (Dr.Jit ``Float`` of 3 each, which
    may be gradient-tracking leaves)."""

    shape: str
    v0: np.ndarray
    faces: np.ndarray
    centre: np.ndarray
    values: dict[str, object] = field(default_factory=dict)
    _v0: mi.Point3f | None = field(default=None, repr=False)   # v0 as a Dr.Jit Point3f

    @classmethod
    def of(cls, params: mi.SceneParameters, shape: str) -> ShapePose:
        v0 = np.asarray(params[f"{shape}.vertex_positions"], np.float64).reshape(-1, 3)
        faces = np.asarray(params[f"{shape}.faces"], np.int64).reshape(-1, 3)
        centre = (v0.min(axis=0) + v0.max(axis=0)) / 2
        pose = cls(shape, v0, faces, centre)
        for kind in POSE_KEYS:
            value = mi.Float(np.zeros(3, np.float32))
            dr.make_opaque(value)
            pose.values[kind] = value
        pose._v0 = mi.Point3f(*(mi.Float(v0[:, i].astype(np.float32)) for i in range(3)))
        return pose

    @property
    def radius(self) -> float:
        """The largest distance of a vertex from the centre (scene units)."""
        return float(np.max(np.linalg.norm(self.v0 - self.centre, axis=1))) if len(self.v0) else 0.0

    def write(self, params: mi.SceneParameters) -> None:
        """Set the mesh's ``vertex_positions`` from the current pose (differentiably); the caller
        calls ``params.update()``."""
        t, rotation = self.values[TRANSLATE], _rotation_dr(self.values[ROTATE])
        assert self._v0 is not None   # set by of()
        d = self._v0 - mi.Point3f(*(float(x) for x in self.centre))
        moved = [rotation[i][0] * d.x + rotation[i][1] * d.y + rotation[i][2] * d.z
                 + float(self.centre[i]) + dr.gather(mi.Float, t, i) for i in range(3)]
        params[f"{self.shape}.vertex_positions"] = dr.ravel(mi.Point3f(*moved))

    def vertices(self, translate: np.ndarray, rotate: np.ndarray) -> np.ndarray:
        """The vertices a pose would give, ``(N, 3)`` float64 (numpy: the safety check's)."""
        matrix = pose_matrix(translate, rotate, self.centre)
        return self.v0 @ matrix[:3, :3].T + matrix[:3, 3]

    def report(self, translate: np.ndarray, rotate: np.ndarray) -> dict:
        """The pose as a user reads it: the values, ``D`` 4x4 and the XML to paste back."""
        matrix = pose_matrix(translate, rotate, self.centre)
        return {"shape": self.shape, "translate": [float(x) for x in translate],
                "rotate": [float(x) for x in rotate], "centre": [float(x) for x in self.centre],
                "matrix": matrix.tolist(), "xml": transform_xml(translate, rotate, self.centre)}


def refusal(before: np.ndarray, after: np.ndarray, faces: np.ndarray) -> str | None:
    """Why vertices ``after`` ``(N, 3)`` may not replace ``before``: non-finite vertices, or
    triangles whose normal turned by more than 90 degrees (inverted); None when they may."""
    if not np.all(np.isfinite(after)):
        return "non-finite vertices"
    if not len(faces):
        return None

    def normals(v: np.ndarray) -> np.ndarray:
        a, b, c = v[faces[:, 0]], v[faces[:, 1]], v[faces[:, 2]]
        return np.cross(b - a, c - a)

    old, new = normals(before), normals(after)
    flipped = np.einsum("ij,ij->i", old, new) < 0
    if flipped.any():
        return "inverted triangles"
    return None

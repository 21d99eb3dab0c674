"""How much of the light a surface reflects stays in the scene.

``closure`` is the share ``c`` of cosine-weighted rays leaving random points of the scene's
reflecting surfaces (the residual domain, area-weighted) that hit another surface, rather than
leaving the scene.

Why the recipe wants it: each bounce that stays in the scene multiplies the light by ``a c`` for a
surface albedo ``a``, so an image's response to an albedo grows like ``a / (1 - a c)``: almost
linear where light escapes (``c`` small), strongly curved in a closed room (``c`` near 1, where
the image goes to infinity as ``a`` goes to 1). A Gauss-Newton step is only as good as the linear
model over its length, so the trust region of Levenberg-Marquardt may grow fast in an open scene
and must grow slowly in a closed one (:mod:`services.solver.optimize.recipe`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from services.solver.sampling.camera import make_sampler
from services.solver.sampling.surface import SurfaceSampler, residual_shapes
from services.solver.scene.load import LoadedScene
from services.solver.seeds import derive_seed

#: Rays of the measurement, and the largest standard error of the share they give (1 / (2 sqrt(RAYS))).
RAYS = 1 << 12
STANDARD_ERROR = 0.5 / RAYS ** 0.5


def closure(scene: LoadedScene, *, rays: int = RAYS, seed: int = 0) -> float | None:
    """The share in ``[0, 1]`` of cosine-weighted rays from the residual domain's surfaces that
    hit a surface (module docstring); None for a scene without a reflecting surface."""
    mi_scene = scene.scene
    if not residual_shapes(mi_scene):
        return None
    with dr.suspend_grad():
        sampler = make_sampler(derive_seed(seed, "closure"), rays)
        points = SurfaceSampler(mi_scene).sample(sampler, rays)
        si = points.si
        si.sh_frame = mi.Frame3f(mi.Vector3f(si.n))
        local = mi.warp.square_to_cosine_hemisphere(sampler.next_2d())
        # the side the point's random ω_o looks from (both sides of a two-sided surface reflect)
        side = dr.select(mi.Frame3f.cos_theta(si.wi) >= 0, 1.0, -1.0)
        direction = si.sh_frame.to_world(mi.Vector3f(local.x, local.y, local.z * side))
        hit = mi_scene.ray_test(si.spawn_ray(direction))
        return float(np.count_nonzero(np.array(hit))) / rays

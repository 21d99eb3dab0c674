"""An environment map's ``data`` as a texture parameter (``<id>.data``). Mitsuba's envmap stores
its data with the wrap-around columns refreshed, a copy derived from the field on every update, so
a gradient read from the field came out zero (``ParameterSet.tracking``). A target brighter than
the initial grey must pull every visible texel up: ``dz/dp`` non-zero, finite and negative in sum,
the same frozen or traced (1e-5 relative: same kernels, same samples)."""

from __future__ import annotations

import numpy as np

from services.solver.estimators.render import PathDepth


def _scene(mi) -> dict:
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 60.0, "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0],
                                                                                up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 12, "height": 12, "rfilter": {"type": "box"}}},
        "env": {"type": "envmap", "bitmap": mi.Bitmap(np.full((4, 8, 3), 0.5, np.float32))},
        "ball": {"type": "sphere", "radius": 0.5, "bsdf": {"type": "diffuse"}},
    }


def test_an_environment_maps_data_gets_its_gradient(mi):
    from services.solver.estimators.losses import ImageLoss
    from services.solver.estimators.methods.prb import Prb
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(mitsuba_dict=_scene(mi))
    problem = Problem(scene, ParameterSet(scene.params, ["env.data"]))
    loss = ImageLoss("l2", np.full((12, 12, 3), 2.0, np.float32))     # brighter than the grey sky
    out = {}
    for freeze in (True, False):
        prb = Prb(depth=PathDepth(None, 3), freeze=freeze)
        _, _, out[freeze] = prb.candidate_and_gradient(problem, None, loss, spp=4, gradient_spp=4, seed=3,
                                                       depth=prb.depth, sensor=0)
    g = out[True]
    assert g.shape == (4 * 10 * 3,)                                     # 8 columns and the 2 wrap-around ones
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 0.0
    assert g.sum() < 0.0                                                # brighter is better
    np.testing.assert_allclose(out[True], out[False], rtol=1e-5, atol=1e-7 * np.abs(g).max())

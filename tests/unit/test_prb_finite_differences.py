"""The reference itself: dz/dp of ``prb`` (one adjoint render) against central finite differences
of the path-traced loss, on a scalar parameter.

Both sides use 1024 spp on a 32x32 Cornell box. The finite differences use common random numbers
(the same seed at p ± h), so paths are identical and only their weights change; with h = 0.02 the
truncation error of the central difference is O(h²) on a loss that is quadratic-ish in p.
Tolerance: 2% relative (measured agreement: ~0.2%).
"""

from __future__ import annotations

import numpy as np
import pytest

from services.solver.estimators.render import PathDepth


@pytest.mark.parametrize("key, component", [("red.reflectance.value", 0), ("light.emitter.radiance.value", 1)])
def test_prb_loss_gradient_matches_central_differences(mi, key, component):
    from services.solver.estimators.losses import image_loss
    from services.solver.estimators.methods import Fields
    from services.solver.estimators.methods.prb import Prb
    from services.solver.estimators.problem import Problem
    from services.solver.estimators.render import render
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="cornell-box", resolution=(32, 32))
    params = ParameterSet(scene.params, [key])
    problem = Problem(scene, params)
    p0 = params.values()
    target = render(problem, spp=256, seed=1, depth=PathDepth(12, None))
    p = p0.copy()
    p[component] *= 0.6                                 # away from the target: a clear gradient
    params.assign(p)

    spp, seed = 1024, 7
    y = render(problem, spp=spp, seed=seed, depth=PathDepth(12, None))
    _, dz_dy = image_loss("l2", y, target)
    adjoint = Prb(depth=PathDepth(12, None)).loss_gradient(problem, Fields(), dz_dy, spp=spp, seed=seed)[component]

    h = 0.02 * p[component]
    losses = []
    for sign in (+1, -1):
        q = p.copy()
        q[component] += sign * h
        params.assign(q)
        losses.append(image_loss("l2", render(problem, spp=spp, seed=seed, depth=PathDepth(12, None)), target)[0])
    finite = (losses[0] - losses[1]) / (2 * h)
    print(f"{key}[{component}]: adjoint {adjoint:.6e} finite differences {finite:.6e}")
    assert np.sign(adjoint) == np.sign(finite)
    assert adjoint == pytest.approx(finite, rel=0.02)

"""``prb``'s Jacobian (``services/solver/estimators/methods/prb.py``): one forward-mode render per
group of scalars that change distinct RGB channels gives exactly what one render per scalar
gives, and the gradient contracted from it agrees with the adjoint pass.

Tolerances: the grouped and per-scalar renders share their samples (same seeds), so they agree
to float32 rounding (1e-5 relative). The contracted and the adjoint ``dz/dp`` are independent
estimates of the same number; one 1024-spp estimate of the red albedo's component varies by ~5%
from seed to seed here, so each side averages four 2048-spp estimates (~2% each) and they must
agree within 8%."""

from __future__ import annotations

import numpy as np
import pytest

from services.solver.estimators.methods.prb import channel_groups
from services.solver.estimators.render import UNBIASED, PathDepth


def test_channel_groups_partition_scalars_with_disjoint_channels():
    rgb = [(0,), (1,), (2,)]
    assert channel_groups(rgb + rgb) == [[0, 1, 2], [3, 4, 5]]                 # two albedos: two renders
    assert channel_groups([(0, 1, 2)] + rgb) == [[0], [1, 2, 3]]              # a roughness needs its own
    assert channel_groups([(0, 1, 2)] * 3) == [[0], [1], [2]]
    assert channel_groups([]) == []


def _greedy(channels):
    """The partition by definition: each scalar in the first group that uses none of its channels."""
    groups, used = [], []
    for i, chans in enumerate(channels):
        for group, taken in zip(groups, used):
            if not taken & set(chans):
                group.append(i)
                taken |= set(chans)
                break
        else:
            groups.append([i])
            used.append(set(chans))
    return groups


def test_channel_groups_is_the_greedy_partition_and_near_linear_in_the_scalars():
    rng = np.random.default_rng(0)
    subsets = [(), (0,), (1,), (2,), (0, 1), (0, 2), (1, 2), (0, 1, 2)]
    for n in (1, 2, 7, 50, 400):
        channels = [subsets[k] for k in rng.integers(0, len(subsets), n)]
        assert channel_groups(channels) == _greedy(channels), n
    # a 100,000-vertex mesh: 300,000 coordinates, each changing all three channels (one group each);
    # comparing every scalar with every group, as before, took 31.6 s at 8,000 vertices and hours here
    vertices = channel_groups([(0, 1, 2)] * 300_000)
    assert len(vertices) == 300_000 and vertices[-1] == [299_999]


def _problem(merge: bool, resolution=(16, 16)):
    from services.solver.estimators.layout import DerivativeLayout
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="cornell-box", resolution=resolution)
    params = ParameterSet(scene.params, ["red.reflectance.value", "green.reflectance.value"])
    problem = Problem(scene, params)
    if not merge:
        problem.layout = DerivativeLayout.full(params.n)
    return problem


def test_grouped_forward_renders_equal_one_render_per_scalar(mi):
    from services.solver.estimators.methods import Fields
    from services.solver.estimators.methods.prb import Prb

    prb = Prb(depth=PathDepth(8, None))
    grouped = prb.gradient_images(_problem(merge=True), Fields(), spp=4, seed=11)
    single = prb.gradient_images(_problem(merge=False), Fields(), spp=4, seed=11)
    assert grouped.shape == single.shape == (6, 16, 16, 3)
    assert np.abs(single).sum() > 0
    np.testing.assert_allclose(grouped, single, rtol=1e-5, atol=1e-7)
    # each scalar's image lives in its own channel only
    assert np.all(grouped[0, ..., 1:] == 0) and np.all(grouped[4, ..., [0, 2]] == 0)


def test_the_contracted_gradient_agrees_with_the_adjoint_pass(mi):
    from services.solver.estimators.losses import image_loss
    from services.solver.estimators.methods import Fields
    from services.solver.estimators.methods.prb import Prb
    from services.solver.estimators.render import render

    problem = _problem(merge=True)
    target = render(problem, spp=256, seed=1, depth=UNBIASED)
    problem.parameters.assign(problem.parameters.values() * 0.6)       # away from the target

    def loss(y):
        return image_loss("l2", y, target)

    prb = Prb(depth=UNBIASED)
    contracted, adjoint = [], []
    for seed in range(4):
        _, _, g, images = prb.candidate_gradient_and_images(problem, Fields(), loss, spp=2048, gradient_spp=2048,
                                                            seed=seed, depth=UNBIASED)
        contracted.append(g)
        adjoint.append(prb.candidate_and_gradient(problem, Fields(), loss, spp=2048, gradient_spp=2048, seed=10 + seed,
                                                  depth=UNBIASED)[2])
    assert images.shape == (6, 16, 16, 3)
    contracted, adjoint = np.mean(contracted, 0), np.mean(adjoint, 0)
    assert np.argmax(np.abs(adjoint)) == 0 and adjoint[0] < 0                  # red's red: towards the target
    assert contracted[0] == pytest.approx(adjoint[0], rel=0.08)


def test_prb_is_never_built_without_a_depth():
    from services.solver.estimators.methods import make_method

    with pytest.raises(ValueError, match="PathDepth"):
        make_method("prb")
    with pytest.raises(ValueError, match="never end"):
        PathDepth(None, None)

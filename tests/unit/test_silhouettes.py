"""Silhouettes of a geometry job's moved shapes (:mod:`services.solver.scene.silhouettes`): the
covered fraction per pixel follows the shape, and the overlay draws what the dashboard says."""

from __future__ import annotations

import numpy as np
import pytest

from services.solver.scene.silhouettes import CURRENT, TARGET, outline, overlay


def _block(resolution: int = 16):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="pose-block", resolution=(resolution, resolution))
    return scene, ParameterSet(scene.params, ["block.to_world.translate"])


def test_a_silhouette_covers_the_block_and_moves_with_it(mi):
    from services.solver.scene.silhouettes import silhouette

    scene, params = _block()
    before = silhouette(scene.scene, ["block"], scene.sensor(0))
    assert before.shape == (16, 16) and before.min() >= 0.0 and before.max() == 1.0
    assert 5 < before.sum() < 0.5 * before.size                    # the block, not the floor
    assert set(np.unique(before * 4)) <= {0.0, 1.0, 2.0, 3.0, 4.0}  # 2 x 2 rays per pixel
    columns = np.arange(16)
    centre = (before.sum(0) * columns).sum() / before.sum()
    params.assign(np.array([0.15, 0.0, 0.0]))                       # sideways, by a fifth of the view
    after = silhouette(scene.scene, ["block"], scene.sensor(0))
    moved = (after.sum(0) * columns).sum() / after.sum() - centre
    assert abs(moved) > 1.0, moved                                  # pixels
    assert abs(after.sum() - before.sum()) < 0.35 * before.sum()    # the same block, elsewhere
    with pytest.raises(ValueError, match="no shape"):
        silhouette(scene.scene, ["bunny"], scene.sensor(0))


def test_the_overlay_tints_the_current_silhouette_and_outlines_the_targets():
    target = np.full((8, 8, 3), 0.2, np.float32)
    current = np.zeros((8, 8), np.float32)
    current[2:5, 2:5] = 1.0
    wanted = np.zeros((8, 8), np.float32)
    wanted[3:7, 3:7] = 1.0
    image = overlay(target, current, wanted)
    assert image.shape == (8, 8, 3) and image.dtype == np.float32
    edge = outline(wanted)
    assert edge[3, 3] and edge[6, 6] and not edge[4, 4] and not edge[0, 0]
    np.testing.assert_allclose(image[edge], np.broadcast_to(TARGET, (int(edge.sum()), 3)))
    tinted = image[2, 2]                                            # inside the current, off the outline
    assert np.dot(tinted - image[0, 0], CURRENT - CURRENT.mean()) > 0
    np.testing.assert_allclose(image[0, 0], image[0, 0].mean())     # grey outside both
    assert np.array_equal(overlay(target, current), overlay(target, current, None))

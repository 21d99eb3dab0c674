"""Regularization of texture parameters (the job's ``textures`` settings), applied to the gradient
``dz/dp`` ``(P,)`` before the optimizer's step; scalars that are not texels are left alone.

``smoothness``  adds the gradient of a penalty on differences between neighbouring texels (right
                and down neighbours, per channel), averaged over the ``D`` neighbour pairs so that
                the weight does not depend on the texture's size:

                * ``laplacian``: ``R = w / D · Σ (p_i - p_j)²``, gradient ``2 w / D · Σ_j (p_i - p_j)``
                  (``-2 w / D`` times the texture's graph Laplacian): smooths everywhere;
                * ``tv``: ``R = w / D · Σ sqrt((p_i - p_j)² + ε²)`` (total variation, ε = 1e-3 keeps
                  it differentiable): favours piecewise-constant textures, keeps edges.

                The reported loss stays the image loss ``z(y)``; ``R`` enters only the step.
``resolution``  ``auto``: a texture whose footprint is too small for its texels moves in blocks of
                ``B x B`` texels throughout (:mod:`.rules.texture_resolution`); the gradient is
                averaged over each block as in a coarse stage below.
``coarse_to_fine``  ``L`` levels: the first half of the iterations is split evenly into ``L`` stages
                whose gradient is averaged over blocks of ``2^L, ..., 2`` texels per side and
                given to every texel of the block. A texture that starts uniform within each block
                (a constant ``init``) then stays so: the stage optimizes the texture at
                ``1/2^l`` of its resolution (upsampled by repetition), and the second half at the
                full resolution.
"""

from __future__ import annotations

import numpy as np

from schemas.job import TextureSettings
from services.solver.optimize.textures import TextureReport

#: ε of the smoothed total variation.
TV_EPSILON = 1e-3


def block_size(settings: TextureSettings, k: int, iterations: int) -> int:
    """Texels per side whose gradient is averaged at iteration ``k`` (1: full resolution)."""
    levels = settings.coarse_to_fine
    half = iterations // 2
    if levels == 0 or k >= half:
        return 1
    stage = min(levels - 1, k * levels // max(half, 1))
    return 2 ** (levels - stage)


def smoothness_gradient(texture: np.ndarray, kind: str, weight: float) -> np.ndarray:
    """Gradient of the smoothness penalty (module docstring) of ``texture`` ``(H, W, C)``."""
    t = np.asarray(texture, np.float64)
    height, width, channels = t.shape
    pairs = max(((height - 1) * width + height * (width - 1)) * channels, 1)
    out = np.zeros_like(t)
    for axis in (0, 1):
        diff = np.diff(t, axis=axis)              # p_{next} - p_i, one per neighbour pair
        if kind == "laplacian":
            d = 2.0 * diff
        else:
            d = diff / np.sqrt(diff * diff + TV_EPSILON ** 2)
        # dR/dp_i gets -d from the pair (i, next) and +d from the pair (previous, i)
        lower = [slice(None)] * 3
        upper = [slice(None)] * 3
        lower[axis], upper[axis] = slice(0, -1), slice(1, None)
        out[tuple(lower)] -= d
        out[tuple(upper)] += d
    return weight / pairs * out


def pooled(gradient: np.ndarray, block: int) -> np.ndarray:
    """``gradient`` ``(H, W, C)`` averaged over ``block x block`` blocks (partial blocks at the
    edges average what they hold) and repeated over each block."""
    if block <= 1:
        return gradient
    height, width, channels = gradient.shape
    rows, cols = -(-height // block), -(-width // block)
    padded = np.zeros((rows * block, cols * block, channels))
    counts = np.zeros((rows * block, cols * block, 1))
    padded[:height, :width] = gradient
    counts[:height, :width] = 1.0
    sums = padded.reshape(rows, block, cols, block, channels).sum(axis=(1, 3))
    n = counts.reshape(rows, block, cols, block, 1).sum(axis=(1, 3))
    mean = sums / np.maximum(n, 1.0)
    return np.repeat(np.repeat(mean, block, axis=0), block, axis=1)[:height, :width]


def regularized(report: TextureReport, settings: TextureSettings, gradient: np.ndarray, parameters: np.ndarray,
                k: int, iterations: int, blocks: dict[str, int] | None = None) -> np.ndarray:
    """``dz/dp`` ``(P,)`` with the textures' smoothness gradient added and averaged over blocks:
    a texture's own ``blocks[key]`` (the resolution the recipe matched to its footprint) or, during
    the coarse stages, the schedule's, whichever is larger; unchanged for a job without a texture
    or without settings."""
    stage = block_size(settings, k, iterations)
    blocks = blocks or {}
    if not report or (settings.smoothness == "none" and stage == 1 and max(blocks.values(), default=1) == 1):
        return gradient
    out = np.array(gradient, np.float64)
    for texture in report.textures:
        where = slice(texture.offset, texture.offset + texture.size)
        g = out[where].reshape(texture.shape)
        if settings.smoothness != "none":
            g = g + smoothness_gradient(parameters[where].reshape(texture.shape), settings.smoothness,
                                        settings.smoothness_weight)
        out[where] = pooled(g, max(stage, blocks.get(texture.key, 1))).reshape(-1)
    return out

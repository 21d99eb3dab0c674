"""A texture's resolution, matched to the pixels that see it.

Rule: with ``textures.resolution: "auto"``, a texture whose texels are seen by fewer than
:data:`PIXELS_PER_TEXEL` pixels each (the median over its footprint,
:func:`services.solver.scene.footprint.pixels_per_texel`) is optimized in blocks of the smallest
power of two whose blocks that many pixels see (at most :data:`MAX_BLOCK`); ``"full"`` keeps
every texel free.

Why: the images cannot pin down more texels than pixels see; a block's standard error is finite
where a texel's is not.

Measured: ``python -m bench.investigations.texture_footprint`` (matched to the pixels: 28.4 dB
against 17.6 dB texel by texel; ``bench/results/texture_footprint.md``).
"""

from __future__ import annotations

import numpy as np

from schemas.job import JobSpec
from services.solver.optimize.recipe import Recipe
from services.solver.optimize.rules.inputs import Decide, Measures, Parameters
from services.solver.scene.footprint import pixels_per_texel

#: A texture needs this many pixels per texel (median over its footprint) to be optimized at its own resolution.
PIXELS_PER_TEXEL = 4
#: The largest block of texels a texture's resolution is matched with.
MAX_BLOCK = 16


def texture_blocks(spec: JobSpec, parameters: Parameters, measures: Measures,
                   decide: Decide) -> tuple[tuple[str, int], ...]:
    """Each texture's block side (module docstring): 1 (its own resolution) or a power of two."""
    out = []
    for key, shape in parameters.textures:
        counts = measures.footprint(key, shape)
        per_texel = pixels_per_texel(counts)
        seen = (f"its footprint: {int(counts.sum())} pixels of the target views see its {shape[0]}x{shape[1]} "
                f"texels directly ({counts.sum() / counts.size:.2g} per texel; {per_texel:.2g} per texel seen, median)")
        if spec.textures.resolution == "full" or per_texel >= PIXELS_PER_TEXEL or not counts.any():
            why = ("the job's textures.resolution 'full'" if spec.textures.resolution == "full" else
                   "no pixel sees it directly (a texture lit or seen through interreflection): nothing to match"
                   if not counts.any() else f"enough pixels for every texel (at least {PIXELS_PER_TEXEL})")
            decide(f"resolution {key}", f"{shape[0]}x{shape[1]}", f"{seen}: {why}")
            out.append((key, 1))
            continue
        block = 2
        while block < MAX_BLOCK and pixels_per_texel(counts, block) < PIXELS_PER_TEXEL:
            block *= 2
        decide(f"resolution {key}", f"{-(-shape[0] // block)}x{-(-shape[1] // block)}",
               f"{seen}: the images cannot pin down its texels (fewer than {PIXELS_PER_TEXEL} pixels per texel), so "
               f"blocks of {block}x{block} texels move together, each seen by {pixels_per_texel(counts, block):.2g} "
               f"pixels (median): detail finer than {block} texels is not recovered, the answer holds the texture's "
               f"{block}x{block} block means (on the textured box's wall, whose checker and ramps change from texel to "
               f"texel, its 2x2 block means are themselves 29.7 dB from it); textures.resolution 'full' keeps every "
               f"texel free, at the images' noise (bench.investigations.texture_footprint)")
        out.append((key, block))
    return tuple(out)


def undetermined_texels(recipe: Recipe, measures: Measures,
                        shapes: dict[str, tuple[int, ...]]) -> dict[str, np.ndarray]:
    """Per texture (``shapes``: key -> ``(H, W, C)``), ``(H, W)`` true where the texel's block at
    the recipe's resolution is seen by less than one pixel: the images do not determine it (its
    standard error is infinite)."""
    out = {}
    for key, block in recipe.texture_blocks:
        counts = measures.footprint(key, shapes[key])
        height, width = counts.shape
        rows, columns = -(-height // block), -(-width // block)
        padded = np.zeros((rows * block, columns * block))
        padded[:height, :width] = counts
        sums = padded.reshape(rows, block, columns, block).sum((1, 3))
        out[key] = np.repeat(np.repeat(sums < 1.0, block, axis=0), block, axis=1)[:height, :width]
    return out

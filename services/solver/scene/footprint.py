"""A texture's footprint: how many camera pixels see each of its texels directly.

For each target view, one ray through each pixel's centre; where it first hits a shape whose BSDF
holds the texture, the hit's ``(u, v)`` is looked up as Mitsuba's bitmap does, bilinearly between
the four texels around ``(row, column) = (v H - 1/2, u W - 1/2)`` of the ``(H, W, C)`` texture
(the bitmap's own ``to_uv`` taken as the identity), and the pixel counts for each of them with
the lookup's weight. Summed over the views: ``(H, W)`` pixel counts.

Why the recipe wants it: each pixel gives one equation per channel, so a texture whose texels
outnumber the pixels that see them cannot be pinned down by the images alone. Its noise-driven
texels end at whatever the optimizer's noise leaves them (salt and pepper, texels pinned at the
bounds); :mod:`services.solver.optimize.rules.texture_resolution` then matches the texture's resolution to its
footprint. Textures seen only through interreflection, and those of emitters, have no direct
footprint (every count is 0).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from services.solver.jit_types import Float
from services.solver.sampling.camera import WAVELENGTH_SAMPLE
from services.solver.scene.load import LoadedScene

#: The time of the rays (a static scene).
TIME: Float = 0.0


def texel_footprint(scene: LoadedScene, key: str, shape: tuple[int, ...], sensors: list[int]) -> np.ndarray:
    """``(H, W)`` pixel counts (weighted by the bilinear lookup) of the pixels of ``sensors`` whose
    first hit reads texel ``(row, column)`` of the texture ``key`` (a BSDF's
    ``<bsdf id>.<texture>.data``) of shape ``(H, W, C)``."""
    height, width = shape[0], shape[1]
    owner = key.split(".", 1)[0]
    shapes = [s for s in scene.scene.shapes() if s.bsdf() is not None and s.bsdf().id() == owner]
    counts = np.zeros((height, width), np.float64)
    if not shapes:
        return counts
    with dr.suspend_grad():
        for index in sensors:
            sensor = scene.sensor(index)
            w, h = scene.resolution(index)
            pixel = dr.arange(mi.UInt32, w * h)
            position = mi.Point2f((mi.Float(pixel % w) + 0.5) / w, (mi.Float(pixel // w) + 0.5) / h)
            ray, _ = sensor.sample_ray(TIME, WAVELENGTH_SAMPLE, position, mi.Point2f(0.5, 0.5))
            si = scene.scene.ray_intersect(ray)
            hit = dr.zeros(mi.Bool, w * h)
            for s in shapes:
                hit |= si.shape == mi.ShapePtr(s)
            seen = np.array(hit & si.is_valid(), dtype=bool)
            u, v = np.array(si.uv.x, np.float64)[seen], np.array(si.uv.y, np.float64)[seen]
            _splat(counts, v * height - 0.5, u * width - 0.5)
    return counts


def _splat(counts: np.ndarray, y: np.ndarray, x: np.ndarray) -> None:
    """Add each pixel to the four texels its bilinear lookup at texel coordinates ``(y, x)`` reads,
    with the lookup's weights (clamped at the edges)."""
    height, width = counts.shape
    y0, x0 = np.floor(y), np.floor(x)
    fy, fx = y - y0, x - x0
    for dy, wy in ((0, 1 - fy), (1, fy)):
        for dx, wx in ((0, 1 - fx), (1, fx)):
            rows = np.clip(y0 + dy, 0, height - 1).astype(np.int64)
            columns = np.clip(x0 + dx, 0, width - 1).astype(np.int64)
            np.add.at(counts, (rows, columns), wy * wx)


def pixels_per_texel(counts: np.ndarray, block: int = 1) -> float:
    """The median pixel count of the texture's blocks of ``block x block`` texels that any pixel
    sees (0 when none is): at the texture's own resolution for ``block`` 1. Texels no pixel sees
    stay unseen at any resolution, so they do not count."""
    height, width = counts.shape
    hb, wb = max(1, height // block), max(1, width // block)
    cropped = counts[:hb * block, :wb * block] if block > 1 else counts
    blocks = cropped.reshape(hb, block, wb, block).sum((1, 3)) if block > 1 else cropped
    seen = blocks[blocks > 0]
    return float(np.median(seen)) if seen.size else 0.0

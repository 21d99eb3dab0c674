"""Silhouettes of the shapes a geometry job moves, for people (the dashboard, the files): where the
current shapes cover a view, against where the target's cover it.

A silhouette is the fraction of a pixel's area whose camera ray first hits one of the moved
shapes: ``S(x) = (1/n²) Σ_j 1[hit(ray(x, u_j)) ∈ shapes]`` over an ``n x n`` grid of
sub-pixel positions ``u_j`` (no sampler: the same every iteration, so a change is the shape's
motion, not noise). It costs one ray cast per sub-pixel, no shading.

:func:`overlay` composes what the dashboard shows: the target image in grey, the current
silhouette's area tinted orange, and the target's silhouette outlined in cyan when it is known (a
synthetic target's values; an image target has none to draw).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from services.solver.jit_types import Float
from services.solver.sampling.camera import WAVELENGTH_SAMPLE

#: The time of the rays (a still scene).
TIME: Float = 0.0
#: Display colours in [0, 1]: the current silhouette's tint and the target's outline.
CURRENT = np.array([1.0, 0.55, 0.1], np.float32)
TARGET = np.array([0.1, 0.9, 1.0], np.float32)


def silhouette(scene: mi.Scene, shape_ids: list[str], sensor: mi.Sensor, supersample: int = 2) -> np.ndarray:
    """``S`` (module docstring) of the shapes named ``shape_ids`` seen by ``sensor``, ``(H, W)``
    float32 in [0, 1], with ``supersample`` x ``supersample`` rays per pixel."""
    if supersample < 1:
        raise ValueError(f"supersample must be at least 1, got {supersample}")
    shapes = [s for s in scene.shapes() if s.id() in set(shape_ids)]
    missing = set(shape_ids) - {s.id() for s in shapes}
    if missing:
        raise ValueError(f"no shape {sorted(missing)} in the scene")
    width, height = (int(v) for v in sensor.film().crop_size())
    n = supersample
    index = dr.arange(mi.UInt32, width * height * n * n)
    pixel, sub = index // (n * n), index % (n * n)
    x = mi.Float(pixel % width) + (mi.Float(sub % n) + 0.5) / n
    y = mi.Float(pixel // width) + (mi.Float(sub // n) + 0.5) / n
    with dr.suspend_grad():
        ray, _ = sensor.sample_ray(TIME, WAVELENGTH_SAMPLE, mi.Point2f(x / width, y / height), mi.Point2f(0.5, 0.5))
        si = scene.ray_intersect(ray)
        hit = mi.Bool(False)
        for shape in shapes:
            hit |= si.is_valid() & (si.shape == mi.ShapePtr(shape))
    covered = np.asarray(dr.select(hit, 1.0, 0.0), np.float32).reshape(height, width, n * n)
    return covered.mean(axis=2)


def outline(mask: np.ndarray, level: float = 0.5) -> np.ndarray:
    """Pixels on the boundary of ``mask >= level`` (inside pixels with an outside 4-neighbour),
    ``(H, W)`` bool."""
    inside = mask >= level
    padded = np.pad(inside, 1, mode="edge")
    outside_near = ~padded[:-2, 1:-1] | ~padded[2:, 1:-1] | ~padded[1:-1, :-2] | ~padded[1:-1, 2:]
    return inside & outside_near


def overlay(target: np.ndarray, current: np.ndarray, target_silhouette: np.ndarray | None = None) -> np.ndarray:
    """The dashboard's silhouette image ``(H, W, 3)`` float32 in display space [0, 1]: ``target``
    ``(H, W, 3)`` (linear radiance) as grey, ``current`` ``(H, W)`` tinted in :data:`CURRENT`, and
    the outline of ``target_silhouette`` ``(H, W)`` in :data:`TARGET` when given."""
    luminance = np.asarray(target, np.float32) @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    grey = np.clip(luminance / max(float(np.percentile(luminance, 99)), 1e-6), 0.0, 1.0) ** (1 / 2.2)
    image = np.repeat((0.6 * grey)[..., None], 3, axis=2)
    alpha = 0.6 * np.clip(current, 0.0, 1.0)[..., None]
    image = (1 - alpha) * image + alpha * CURRENT
    if target_silhouette is not None:
        image[outline(target_silhouette)] = TARGET
    return image.astype(np.float32)

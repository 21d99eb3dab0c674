"""Image encodings of the store: PNG previews (sRGB renders, diverging gradient maps) and float data.

Pure numpy + Pillow, no Mitsuba: the API process serves and the dashboard shows these files.
"""

from __future__ import annotations

import io

import numpy as np
from PIL import Image, PngImagePlugin

# Anchors of a blue-white-red diverging map (Moreland's "cool to warm"), from -1 to +1.
_DIVERGING = np.array([
    [0.230, 0.299, 0.754],
    [0.552, 0.690, 0.996],
    [0.865, 0.865, 0.865],
    [0.958, 0.603, 0.482],
    [0.706, 0.016, 0.150],
])


def diverging_colors(t: np.ndarray) -> np.ndarray:
    """Map values in ``[-1, 1]`` to RGB in ``[0, 1]`` (``(...,)`` -> ``(..., 3)``); 0 is grey."""
    x = (np.clip(np.nan_to_num(t), -1.0, 1.0) + 1.0) * 0.5 * (len(_DIVERGING) - 1)
    lo = np.minimum(np.floor(x).astype(int), len(_DIVERGING) - 2)
    frac = (x - lo)[..., None]
    return _DIVERGING[lo] * (1 - frac) + _DIVERGING[lo + 1] * frac


def gradient_scale(image: np.ndarray, percentile: float = 99.5) -> float:
    """Symmetric colour-map range of a gradient image: a high percentile of ``|sum over RGB|``
    (robust to a few fireflies); 0 for an all-zero image."""
    values = np.abs(np.asarray(image, np.float64).sum(-1))
    finite = values[np.isfinite(values)]
    return float(np.percentile(finite, percentile)) if finite.size else 0.0


def _png(rgb8: np.ndarray, text: dict[str, str]) -> bytes:
    info = PngImagePlugin.PngInfo()
    for k, v in text.items():
        info.add_text(k, v)
    buffer = io.BytesIO()
    Image.fromarray(rgb8, "RGB").save(buffer, format="PNG", pnginfo=info)
    return buffer.getvalue()


def gradient_png(image: np.ndarray, scale: float | None = None) -> tuple[bytes, float]:
    """PNG of one scalar's gradient image ``(H, W, 3)``: the RGB sum through the diverging map,
    red positive, blue negative, grey zero. Returns the PNG and the scale (value of full red);
    the scale is also stored in the PNG's ``ndrf:scale`` text chunk."""
    scale = gradient_scale(image) if scale is None else float(scale)
    t = np.asarray(image, np.float64).sum(-1) / (scale if scale > 0 else 1.0)
    rgb8 = (diverging_colors(t) * 255 + 0.5).astype(np.uint8)
    return _png(rgb8, {"ndrf:scale": repr(scale)}), scale


def srgb_png(image: np.ndarray, exposure: float = 1.0) -> bytes:
    """PNG of a linear RGB render ``(H, W, 3)`` (clamped, sRGB transfer curve)."""
    x = np.clip(np.nan_to_num(np.asarray(image, np.float64)[..., :3] * exposure), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return _png((srgb * 255 + 0.5).astype(np.uint8), {})


def npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array))
    return buffer.getvalue()

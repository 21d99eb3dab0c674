"""Image encodings of the store: PNG previews (sRGB renders, diverging gradient maps) and float data
(``.npy``, OpenEXR).

Pure numpy + Pillow + OpenEXR (the Academy Software Foundation's binding), no Mitsuba: the worker's
host process writes these files (it never loads Mitsuba, see the import contracts in pyproject.toml),
the API process serves them and the dashboard shows them.
"""

from __future__ import annotations

import io

import numpy as np
import OpenEXR
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


def display_png(image: np.ndarray) -> bytes:
    """PNG of an image already in display space ``(H, W, 3)`` in [0, 1] (a silhouette overlay)."""
    x = np.clip(np.nan_to_num(np.asarray(image, np.float64)[..., :3]), 0.0, 1.0)
    return _png((x * 255 + 0.5).astype(np.uint8), {})


def npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array))
    return buffer.getvalue()


#: OpenEXR channel names by channel count (Mitsuba's: ``Y``, ``YA``, ``RGB``, ``RGBA``); other counts
#: get ``C00``, ``C01``, ... (zero-padded: a file's channels are stored in alphabetical order, so the
#: names keep the array's channel order).
_EXR_CHANNELS = {1: ("Y",), 2: ("Y", "A"), 3: ("R", "G", "B"), 4: ("R", "G", "B", "A")}


def exr_bytes(array: np.ndarray) -> bytes:
    """A single-part scanline OpenEXR file of ``array`` (``(H, W)`` or ``(H, W, C)``), 32-bit float
    channels, lossless ZIP compression: the values as they are (no clamping, no transfer curve),
    readable by Mitsuba, OpenEXR, Blender and image viewers. Written by the Academy Software
    Foundation's ``OpenEXR`` binding into memory (no Mitsuba in this process)."""
    image = np.asarray(array, np.float32)
    if image.ndim == 2:
        image = image[..., None]
    if image.ndim != 3 or 0 in image.shape:
        raise ValueError(f"an EXR image is (H, W) or (H, W, C) with no empty axis, not {np.shape(array)}")
    count = image.shape[-1]
    names = _EXR_CHANNELS.get(count) or tuple(f"C{i:02d}" for i in range(count))
    channels = {name: np.ascontiguousarray(image[..., i]) for i, name in enumerate(names)}
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    buffer = io.BytesIO()
    OpenEXR.File(header, channels).write(buffer)
    return buffer.getvalue()

"""Decoding of uploaded target images (EXR, PNG, NPY) into linear RGB float arrays."""

from __future__ import annotations

import io

import numpy as np

_PNG = b"\x89PNG\r\n\x1a\n"
_EXR = b"\x76\x2f\x31\x01"
_NPY = b"\x93NUMPY"


class ImageDecodeError(ValueError):
    """The bytes are not a usable target image (format, shape or values)."""


def srgb_to_linear(x: np.ndarray) -> np.ndarray:
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)


def image_format(data: bytes) -> str:
    for magic, name in ((_PNG, "png"), (_EXR, "exr"), (_NPY, "npy")):
        if data.startswith(magic):
            return name
    raise ImageDecodeError("unknown image format: expected EXR, PNG or NPY")


def decode_image(data: bytes) -> np.ndarray:
    """``(H, W, 3)`` float32 linear RGB. PNG is 8/16-bit sRGB; EXR and NPY are linear already.
    Alpha is dropped, grey is broadcast to RGB. Raises :class:`ImageDecodeError` for anything else,
    including non-finite or negative values."""
    kind = image_format(data)
    try:
        if kind == "npy":
            array = np.load(io.BytesIO(data), allow_pickle=False).astype(np.float32)
        elif kind == "png":
            from PIL import Image

            with Image.open(io.BytesIO(data)) as img:
                raw = np.asarray(img)
                bits = 16 if raw.dtype == np.uint16 or img.mode.startswith("I;16") else 8
                array = srgb_to_linear(raw.astype(np.float64) / (2 ** bits - 1)).astype(np.float32)
        else:
            from services.backend import use_mitsuba

            mi = use_mitsuba()
            bitmap = mi.Bitmap(mi.MemoryStream(data) if hasattr(mi, "MemoryStream") else io.BytesIO(data))
            array = np.array(bitmap, dtype=np.float32)
    except ImageDecodeError:
        raise
    except Exception as exc:  # the decoders raise many types; all mean "not a valid image"
        raise ImageDecodeError(f"could not decode the {kind.upper()} image: {exc}") from None
    if array.ndim == 2:
        array = array[..., None]
    if array.ndim != 3 or array.shape[2] not in (1, 3, 4):
        raise ImageDecodeError(f"expected an H x W image with 1, 3 or 4 channels, got shape {array.shape}")
    if array.shape[2] == 1:
        array = np.repeat(array, 3, axis=2)
    array = np.ascontiguousarray(array[..., :3])
    if not np.all(np.isfinite(array)):
        raise ImageDecodeError("the image contains NaN or Inf values")
    if np.any(array < 0):
        raise ImageDecodeError("the image contains negative values")
    return array

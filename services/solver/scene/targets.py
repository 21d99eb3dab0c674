"""Decoding of uploaded target images (EXR, PNG, JPEG, NPY) into linear RGB float arrays.

PNG, JPEG and EXR go through Mitsuba's own bitmap reader (sRGB-encoded formats are linearised by
it), NPY through numpy without pickles. This runs in the sandboxed process that loads the job;
the service checks each image's header (format, pixel count) before it gets here.
"""

from __future__ import annotations

import io

import numpy as np

_MAGIC = {b"\x89PNG\r\n\x1a\n": "png", b"\x76\x2f\x31\x01": "exr", b"\x93NUMPY": "npy", b"\xff\xd8\xff": "jpeg"}


class ImageDecodeError(ValueError):
    """The bytes are not a usable target image (format, shape or values)."""


def image_format(data: bytes) -> str:
    for magic, name in _MAGIC.items():
        if data.startswith(magic):
            return name
    raise ImageDecodeError("unknown image format: expected EXR, PNG, JPEG or NPY")


def _bitmap(data: bytes) -> np.ndarray:
    from services.solver.backend import use_mitsuba

    mi = use_mitsuba()
    stream = mi.MemoryStream()
    stream.write(data)
    stream.seek(0)
    bitmap = mi.Bitmap(stream)
    linear = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=False)
    return np.array(linear, dtype=np.float32)


def decode_image(data: bytes) -> np.ndarray:
    """``(H, W, 3)`` float32 linear RGB; alpha is dropped, grey is broadcast to RGB. Raises
    :class:`ImageDecodeError` for anything else, including non-finite or negative values."""
    kind = image_format(data)
    try:
        if kind == "npy":
            array = np.load(io.BytesIO(data), allow_pickle=False).astype(np.float32)
        else:
            array = _bitmap(data)
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

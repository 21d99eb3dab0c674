"""The store's OpenEXR encoder (``services.store.images.exr_bytes``, the ``OpenEXR`` binding, no
Mitsuba): the files it writes decode, with Mitsuba's OpenEXR reader, to the very float32 values it
was given, channel names and order kept."""

from __future__ import annotations

import io

import numpy as np
import OpenEXR
import pytest

from services.store.images import exr_bytes
from services.uploads.images import ImageInfo, image_header


def _decode(mi, data: bytes) -> tuple[np.ndarray, str]:
    """The pixels (H, W, C) and pixel format Mitsuba reads from an EXR file's bytes."""
    stream = mi.MemoryStream()
    stream.write(data)
    stream.seek(0)
    bitmap = mi.Bitmap(stream, mi.Bitmap.FileFormat.OpenEXR)
    assert bitmap.component_format() == mi.Struct.Type.Float32
    pixels = np.array(bitmap, copy=True)
    return pixels.reshape(*pixels.shape[:2], -1), bitmap.pixel_format().name


@pytest.mark.parametrize(("shape", "pixel_format"), [
    ((64, 64, 3), "RGB"),      # a whole number of 16-line ZIP blocks
    ((37, 19, 1), "Y"),        # an odd height: a short last block
    ((5, 7, 4), "RGBA"),
    ((9, 3, 2), "YA"),
    ((20, 6, 5), "MultiChannel"),
])
def test_exr_decodes_to_the_same_float32_values(mi, shape, pixel_format):
    rng = np.random.default_rng(7)
    noisy = rng.normal(0.0, 10.0, shape).astype(np.float32)       # incompressible
    ramp = np.broadcast_to(np.linspace(0.0, 1.0, shape[1], dtype=np.float32)[None, :, None], shape).copy()
    for image in (noisy, ramp):
        decoded, fmt = _decode(mi, exr_bytes(image))
        assert fmt == pixel_format
        assert decoded.dtype == np.float32 and decoded.shape == shape
        assert np.array_equal(decoded, image)                     # bit for bit, channel order kept


def test_exr_keeps_every_float_and_compresses_smooth_textures(mi):
    image = np.full((32, 32, 3), 0.25, np.float32)
    image[0, 0] = [np.inf, -np.inf, -3.0e38]
    image[1, 1] = [1e-45, -0.0, 65504.0 * 4]                      # a denormal, beyond half's range
    image[2, 2, 0] = np.nan
    data = exr_bytes(image)
    decoded, _ = _decode(mi, data)
    assert np.array_equal(decoded.view(np.uint32), image.view(np.uint32))
    assert len(data) < image.nbytes // 4                          # lossless ZIP compression is on


def test_exr_header_is_what_the_upload_checks_read():
    header = OpenEXR.File(io.BytesIO(exr_bytes(np.zeros((3, 2, 3), np.float32))), header_only=True).header()
    assert header["compression"] == OpenEXR.ZIP_COMPRESSION and header["type"] == OpenEXR.scanlineimage
    assert image_header(exr_bytes(np.zeros((10, 30, 3), np.float32))) == ImageInfo("exr", 30, 10, 3)
    assert image_header(exr_bytes(np.zeros((4, 5), np.float32))) == ImageInfo("exr", 5, 4, 1)
    with pytest.raises(ValueError, match="EXR"):
        exr_bytes(np.zeros((0, 4, 3), np.float32))

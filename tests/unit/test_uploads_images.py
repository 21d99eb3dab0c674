"""Image sizes read from headers only, before any decoder runs (no Mitsuba needed)."""

from __future__ import annotations

import io
import struct
import zlib

import numpy as np
import pytest
from PIL import Image

from services.uploads.images import (
    ImageHeaderError,
    ImageInfo,
    check_image,
    image_header,
)
from services.uploads.scene import InvalidJob
from tests.support.payloads import exr_header, jpeg, npy, png


def test_png_bomb_is_refused_from_its_header():
    """The issue's attack: 3000 x 3000 pixels in ~9 KB (27 M values once broadcast to RGB)."""
    data = png(3000, 3000, "L")
    assert len(data) < 10_000
    assert image_header(data) == ImageInfo("png", 3000, 3000, 1)
    with pytest.raises(InvalidJob) as caught:
        check_image("targets.images[0].data", data, max_pixels=4 << 20)
    assert caught.value.field == "targets.images[0].data"
    assert caught.value.message == "is a 3000 x 3000 PNG image (9000000 pixels); at most 4194304 pixels are " \
                                   "allowed (NDRF_MAX_IMAGE_PIXELS)"


def test_exr_header_claiming_a_huge_image_is_refused():
    data = exr_header(200_000, 100_000)  # no pixel data at all
    assert image_header(data) == ImageInfo("exr", 200_000, 100_000, 3)
    with pytest.raises(InvalidJob, match=r"is a 200000 x 100000 EXR image \(20000000000 pixels\); at most 1000"):
        check_image("t", data, max_pixels=1000)


def test_npy_header_claiming_a_huge_image_is_refused():
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, {"descr": "<f4", "fortran_order": False,
                                                  "shape": (90000, 90000, 3)})
    data = buffer.getvalue() + bytes(48)  # the data of a 2 x 2 x 3 image
    with pytest.raises(ImageHeaderError, match=r"declares shape \(90000, 90000, 3\) of float32 \(97200000000 "
                                               r"bytes of data\), but the file has 48"):
        image_header(data)


@pytest.mark.parametrize("data, expected", [
    (png(7, 5), ImageInfo("png", 7, 5, 3)),
    (png(7, 5, "RGBA"), ImageInfo("png", 7, 5, 4)),
    (png(7, 5, "L"), ImageInfo("png", 7, 5, 1)),
    (png(7, 5, "I;16"), ImageInfo("png", 7, 5, 1)),
    (jpeg(33, 17), ImageInfo("jpeg", 33, 17, 3)),
    (npy(np.zeros((5, 7, 3), np.float32)), ImageInfo("npy", 7, 5, 3)),
    (npy(np.zeros((5, 7), np.uint16)), ImageInfo("npy", 7, 5, 1)),
    (exr_header(7, 5, "ABGR"), ImageInfo("exr", 7, 5, 4)),
    (b"P6\n7 5\n255\n" + bytes(105), ImageInfo("ppm", 7, 5, 3)),
    (b"PF\n7 5\n-1.0\n" + bytes(420), ImageInfo("pfm", 7, 5, 3)),
    (b"Pf\n7 5\n-1.0\n" + bytes(140), ImageInfo("pfm", 7, 5, 1)),
    (b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 5 +X 7\n" + bytes(140), ImageInfo("rgbe", 7, 5, 3)),
], ids=["png", "png rgba", "png grey", "png 16 bit", "jpeg", "npy rgb", "npy grey", "exr", "ppm", "pfm", "pfm grey",
        "rgbe"])
def test_valid_headers_are_read(data, expected):
    assert image_header(data) == expected


def test_bmp_and_tga_headers_are_read():
    buffer = io.BytesIO()
    Image.new("RGB", (7, 5)).save(buffer, format="BMP")
    assert image_header(buffer.getvalue()) == ImageInfo("bmp", 7, 5, 3)
    tga = struct.pack("<BBB9xhhBB", 0, 0, 2, 7, 5, 24, 0) + bytes(105) + bytes(8) + b"TRUEVISION-XFILE.\0"
    assert image_header(tga) == ImageInfo("tga", 7, 5, 3)
    negative = tga[:12] + struct.pack("<h", -1) + tga[14:]
    with pytest.raises(ImageHeaderError, match="declares -1 x 5 pixels"):
        image_header(negative)


def test_png_with_a_forged_size_needs_a_valid_checksum():
    data = bytearray(png(7, 5))
    data[16:24] = struct.pack(">II", 30000, 30000)
    with pytest.raises(ImageHeaderError, match="bad checksum"):
        image_header(bytes(data))
    data[29:33] = struct.pack(">I", zlib.crc32(bytes(data[12:29])))
    assert image_header(bytes(data)).pixels == 900_000_000


CODE = b"{'descr': __import__('os').system('true'), 'fortran_order': False, 'shape': (1, 1)}\n"


@pytest.mark.parametrize("data, fragment", [
    (b"GIF89a" + bytes(20), "unknown image format"),
    (b"", "unknown image format"),
    (png(7, 5)[:20], "PNG header is truncated"),
    (b"\x89PNG\r\n\x1a\n" + struct.pack(">I4s", 13, b"IHDR") + struct.pack(">IIBBBBB", 0, 5, 8, 2, 0, 0, 0)
     + struct.pack(">I", zlib.crc32(b"IHDR" + struct.pack(">IIBBBBB", 0, 5, 8, 2, 0, 0, 0))), "declares 0 x 5"),
    (exr_header(7, 5, flags=0x1000), "multi-part and deep OpenEXR files are not accepted"),
    (exr_header(7, 5)[:-1], "OpenEXR header is truncated"),
    (exr_header(7, 5)[:60], "attribute 'channels' has an invalid size"),
    (npy(np.zeros((5, 7), np.float32))[:-1], "but the file has 139"),
    (npy(np.zeros((5,), np.float32)), "must be H x W or H x W x C"),
    (npy(np.array([[None]], dtype=object)), "is not a plain numeric type"),
    (b"\x93NUMPY\x01\x00" + struct.pack("<H", len(CODE)) + CODE, "not a valid Python literal"),
    (jpeg(33, 17)[:40], "JPEG header is truncated"),
    (b"\xff\xd8\xff\xda\x00\x02", "no frame header (SOF)"),
    (b"#?RADIANCE\n-Y 5 +X 7\n", "no FORMAT line"),
    (b"P6 7 5", "PPM header is malformed"),
], ids=["gif", "empty", "png truncated", "png zero width", "exr multipart", "exr truncated", "exr attribute", "npy short",
        "npy 1d", "npy object", "npy code", "jpeg truncated", "jpeg no sof", "rgbe format", "ppm truncated"])
def test_bad_headers_are_refused(data, fragment):
    with pytest.raises(ImageHeaderError) as caught:
        image_header(data)
    assert fragment in str(caught.value)


def test_accepted_formats_can_be_restricted():
    with pytest.raises(InvalidJob, match="is a JPEG image; accepted here: PNG, EXR, NPY"):
        check_image("t", jpeg(8, 8), 100, formats=("png", "exr", "npy"))
    assert check_image("t", png(8, 8), 64, formats=("png",)).pixels == 64


def test_channels_count_before_decoding_exr_npy_and_png():
    """Issue 38: a 5.7 MB EXR declaring 700 channels (5.5 GiB decoded) passed the pixel cap."""
    import base64

    from schemas.job import JobSpec
    from services.limits import check_target_headers
    from services.settings import Limits
    from tests.support.jobs import small_job

    many = exr_header(1400, 1400, [f"c{i}" for i in range(700)])
    assert image_header(many) == ImageInfo("exr", 1400, 1400, 700) and len(many) < 20_000
    target = {"sensor": 0, "data": base64.b64encode(many).decode()}
    target = {"sensor": 0, "data": base64.b64encode(many).decode()}
    job = JobSpec.model_validate({**small_job(), "targets": {"images": [target]}})
    with pytest.raises(InvalidJob) as caught:
        check_target_headers(job, Limits())
    assert caught.value.field == "targets.images[0].data"
    assert "700 channels (1372000000 values decoded)" in caught.value.message
    assert "NDRF_MAX_IMAGE_VALUES" in caught.value.message and "before decoding" in caught.value.message
    wide = npy(np.zeros((64, 64, 300), np.uint8))
    with pytest.raises(InvalidJob, match="300 channels"):
        check_image("t", wide, max_pixels=64 * 64)
    assert check_image("t", png(64, 64, "RGBA"), max_pixels=64 * 64).values == 64 * 64 * 4   # 4 channels pass

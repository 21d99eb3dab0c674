"""Read an image's size from its header, without decoding a pixel.

Why: decoders allocate from the header. A 9 KB PNG can declare 3000 x 3000 pixels (27 M values
after decoding), an EXR or NPY header can declare any size, and Mitsuba's bitmap readers size
their buffers from 32-bit header fields (a TGA width of -1 becomes 4294967295). So a caller reads
:func:`image_header` first and applies its pixel cap (``NDRF_MAX_IMAGE_PIXELS`` for targets,
``UploadLimits.max_texture_pixels`` for scene textures) before any decoder runs;
:func:`check_image` does both and raises ``InvalidJob`` naming the field and the limit.

Formats: the ones Mitsuba's ``Bitmap`` detects by their first bytes (PNG, JPEG, OpenEXR, RGBE/
Radiance HDR, PFM, PPM (P6), BMP, TGA v2) and NPY (targets). Anything else is refused, as are
multi-part and deep OpenEXR files, a JPEG whose height is defined later (DNL), and an NPY whose
data does not match its header. Only headers are parsed: a compressed body may still be corrupt,
which its decoder reports.
"""

from __future__ import annotations

import ast
import logging
import math
import struct
import zlib
from dataclasses import dataclass

from schemas.errors import InvalidJob

log = logging.getLogger(__name__)

MAX_SIDE = 2**31 - 1  # libpng's and OpenEXR's limit on a side; Mitsuba stores sides as uint32
_NPY_HEADER_BYTES = 10_000  # numpy's own max_header_size
_TEXT_HEADER_BYTES = 64 << 10  # PPM, PFM, RGBE headers
_EXR_ATTRIBUTES = 1000


class ImageHeaderError(ValueError):
    """The bytes are not an image whose header this module can read."""


@dataclass(frozen=True)
class ImageInfo:
    format: str  # png, jpeg, exr, npy, rgbe, pfm, ppm, bmp, tga
    width: int
    height: int
    channels: int

    @property
    def pixels(self) -> int:
        return self.width * self.height

    @property
    def values(self) -> int:
        """Numbers a decoder makes of it: width x height x channels (a channel of a 700-channel EXR
        costs as much as a whole single-channel image)."""
        return self.width * self.height * self.channels


def image_header(data: bytes) -> ImageInfo:
    """Format, width, height and channels from the header; raise :class:`ImageHeaderError` for
    an unknown format or a header that is malformed or declares an empty or oversized image."""
    view = memoryview(data).toreadonly()
    start = bytes(view[:8])
    for magic, reader in _READERS:
        if start.startswith(magic):
            info = reader(view)
            break
    else:
        if len(view) >= 26 and bytes(view[-18:]) == b"TRUEVISION-XFILE.\0":
            info = _tga(view)
        else:
            raise ImageHeaderError("unknown image format: expected PNG, JPEG, OpenEXR, RGBE (.hdr), PFM, PPM, BMP, "
                                   "TGA or NPY")
    if not (1 <= info.width <= MAX_SIDE and 1 <= info.height <= MAX_SIDE):
        raise ImageHeaderError(f"the {info.format.upper()} header declares {info.width} x {info.height} pixels; "
                               f"each side must be between 1 and {MAX_SIDE}")
    return info


def check_image(field: str, data: bytes, max_pixels: int, limit_name: str = "NDRF_MAX_IMAGE_PIXELS",
                formats: tuple[str, ...] | None = None, max_values: int | None = None,
                values_name: str = "4 channels at the pixel limit") -> ImageInfo:
    """:func:`image_header`, then the pixel cap, the cap on decoded values (width x height x
    channels; default ``4 * max_pixels``) and the accepted ``formats``, if given, as
    ``InvalidJob(field, ...)`` naming the limit: the one place every image is sized before it is
    decoded. Call it before decoding."""
    try:
        info = image_header(data)
    except ImageHeaderError as exc:
        raise InvalidJob(field, str(exc)) from None
    if formats is not None and info.format not in formats:
        raise InvalidJob(field, f"is a {info.format.upper()} image; accepted here: "
                                f"{', '.join(f.upper() for f in formats)}")
    if info.pixels > max_pixels:
        raise InvalidJob(field, f"is a {info.width} x {info.height} {info.format.upper()} image "
                                f"({info.pixels} pixels); at most {max_pixels} pixels are allowed ({limit_name})")
    most = 4 * max_pixels if max_values is None else max_values
    if info.values > most:
        raise InvalidJob(field, f"is a {info.width} x {info.height} {info.format.upper()} image of {info.channels} "
                                f"channels ({info.values} values decoded); at most {most} values are allowed "
                                f"({values_name}): refused before decoding")
    log.debug("%s: %s %dx%d, %d channels", field, info.format, info.width, info.height, info.channels)
    return info


def _need(data: memoryview, size: int, what: str) -> None:
    if len(data) < size:
        raise ImageHeaderError(f"the {what} header is truncated")


def _png(data: memoryview) -> ImageInfo:
    """The first chunk must be IHDR (13 bytes, CRC checked); channels by color type."""
    _need(data, 33, "PNG")
    length, kind = struct.unpack_from(">I4s", data, 8)
    if length != 13 or kind != b"IHDR":
        raise ImageHeaderError("the PNG does not start with an IHDR chunk")
    width, height, depth, color = struct.unpack_from(">IIBB", data, 16)
    (crc,) = struct.unpack_from(">I", data, 29)
    if zlib.crc32(data[12:29]) != crc:
        raise ImageHeaderError("the PNG IHDR chunk has a bad checksum")
    channels = {0: 1, 2: 3, 3: 3, 4: 2, 6: 4}.get(color)
    depths = {0: (1, 2, 4, 8, 16), 3: (1, 2, 4, 8)}.get(color, (8, 16))
    if channels is None or depth not in depths:
        raise ImageHeaderError(f"the PNG has an invalid color type {color} / bit depth {depth}")
    return ImageInfo("png", width, height, channels)


_JPEG_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}
_JPEG_SEGMENTS = 10_000  # before the frame header; real files have a few dozen


def _jpeg(data: memoryview) -> ImageInfo:
    """Walk the marker segments from SOI to the first frame header (SOFn)."""
    pos = 2
    for _ in range(_JPEG_SEGMENTS):
        _need(data, pos + 2, "JPEG")
        if data[pos] != 0xFF:
            raise ImageHeaderError("the JPEG has a malformed marker segment")
        while pos < len(data) and data[pos] == 0xFF:  # markers may be padded with 0xFF
            pos += 1
        _need(data, pos + 1, "JPEG")
        marker = data[pos]
        pos += 1
        if marker in (0x01, *range(0xD0, 0xD8)):  # TEM, RSTn: no length
            continue
        if marker in (0xD9, 0xDA) or marker == 0xD8:
            raise ImageHeaderError("the JPEG has no frame header (SOF) before its image data")
        _need(data, pos + 2, "JPEG")
        (length,) = struct.unpack_from(">H", data, pos)
        if length < 2:
            raise ImageHeaderError("the JPEG has a malformed marker segment")
        if marker in _JPEG_SOF:
            _need(data, pos + 8, "JPEG")
            _, height, width, components = struct.unpack_from(">BHHB", data, pos + 2)
            if height == 0:
                raise ImageHeaderError("the JPEG defines its height after the image data (DNL); not accepted")
            return ImageInfo("jpeg", width, height, components)
        pos += length
    raise ImageHeaderError(f"the JPEG has more than {_JPEG_SEGMENTS} marker segments before its frame header")


def _exr(data: memoryview) -> ImageInfo:
    """Single-part scanline or tiled OpenEXR: the ``dataWindow`` (box2i) and ``channels``
    (chlist) attributes of the header."""
    _need(data, 8, "OpenEXR")
    (version,) = struct.unpack_from("<I", data, 4)
    if version & 0xFF != 2:
        raise ImageHeaderError(f"unsupported OpenEXR version {version & 0xFF}")
    if version & 0x1800:
        raise ImageHeaderError("multi-part and deep OpenEXR files are not accepted")
    pos, window, channels = 8, None, None
    for _ in range(_EXR_ATTRIBUTES):
        name, pos = _cstring(data, pos, 256, "OpenEXR")
        if not name:
            break
        kind, pos = _cstring(data, pos, 256, "OpenEXR")
        _need(data, pos + 4, "OpenEXR")
        (size,) = struct.unpack_from("<i", data, pos)
        pos += 4
        if size < 0 or pos + size > len(data):
            raise ImageHeaderError(f"the OpenEXR attribute {name!r} has an invalid size")
        if name == "dataWindow" and kind == "box2i" and size == 16:
            window = struct.unpack_from("<iiii", data, pos)
        elif name == "channels" and kind == "chlist":
            channels = _exr_channels(data[pos:pos + size])
        pos += size
    else:
        raise ImageHeaderError(f"the OpenEXR header has more than {_EXR_ATTRIBUTES} attributes")
    if window is None or channels is None:
        raise ImageHeaderError("the OpenEXR header lacks its dataWindow or channels attribute")
    xmin, ymin, xmax, ymax = window
    return ImageInfo("exr", xmax - xmin + 1, ymax - ymin + 1, channels)


def _exr_channels(value: memoryview) -> int:
    count, pos = 0, 0
    while True:
        name, pos = _cstring(value, pos, 256, "OpenEXR channel list")
        if not name:
            return count
        pos += 16  # pixel type, pLinear + reserved, x and y sampling
        count += 1


def _cstring(data: memoryview, pos: int, limit: int, what: str) -> tuple[str, int]:
    end = bytes(data[pos:pos + limit]).find(b"\0")
    if end < 0:
        raise ImageHeaderError(f"the {what} header is truncated or has an overlong name")
    return bytes(data[pos:pos + end]).decode("latin-1"), pos + end + 1


def _npy(data: memoryview) -> ImageInfo:
    """The header dict (read with ``ast.literal_eval``, at most numpy's 10,000 bytes): a plain
    numeric dtype, a 2-D or 3-D shape, and exactly ``prod(shape) * itemsize`` bytes of data."""
    import numpy as np

    _need(data, 10, "NPY")
    major = data[6]
    if major == 1:
        (length,), start = struct.unpack_from("<H", data, 8), 10
    elif major in (2, 3):
        _need(data, 12, "NPY")
        (length,), start = struct.unpack_from("<I", data, 8), 12
    else:
        raise ImageHeaderError(f"unsupported NPY version {major}")
    if length > _NPY_HEADER_BYTES:
        raise ImageHeaderError(f"the NPY header has {length} bytes; at most {_NPY_HEADER_BYTES} are allowed")
    _need(data, start + length, "NPY")
    try:
        header = ast.literal_eval(bytes(data[start:start + length]).decode("utf-8" if major == 3 else "latin-1"))
    except (ValueError, SyntaxError, UnicodeDecodeError, MemoryError, RecursionError):
        raise ImageHeaderError("the NPY header is not a valid Python literal") from None
    if not isinstance(header, dict) or set(header) != {"descr", "fortran_order", "shape"}:
        raise ImageHeaderError("the NPY header must be a dict with keys descr, fortran_order and shape")
    shape, descr = header["shape"], header["descr"]
    if not isinstance(shape, tuple) or len(shape) not in (2, 3) or \
            not all(isinstance(n, int) and not isinstance(n, bool) and n >= 0 for n in shape):
        raise ImageHeaderError(f"the NPY array must be H x W or H x W x C, not shape {str(shape)[:60]}")
    try:
        dtype = np.dtype(descr) if isinstance(descr, str) else None
    except (TypeError, ValueError):
        dtype = None
    if dtype is None or dtype.kind not in "biuf" or dtype.itemsize > 16:
        raise ImageHeaderError(f"the NPY dtype {str(descr)[:40]!r} is not a plain numeric type")
    height, width = shape[0], shape[1]
    channels = shape[2] if len(shape) == 3 else 1
    expected = math.prod(shape) * dtype.itemsize
    if len(data) - start - length != expected:
        raise ImageHeaderError(f"the NPY header declares shape {shape} of {dtype} ({expected} bytes of data), "
                               f"but the file has {len(data) - start - length}")
    return ImageInfo("npy", width, height, channels)


def _tokens(data: memoryview, start: int, count: int, what: str) -> tuple[list[bytes], int]:
    """``count`` whitespace-separated tokens from ``start``; the offset after the last."""
    head = bytes(data[start:start + _TEXT_HEADER_BYTES])
    tokens: list[bytes] = []
    pos = 0
    while len(tokens) < count:
        while pos < len(head) and head[pos] in b" \t\r\n":
            pos += 1
        end = pos
        while end < len(head) and head[end] not in b" \t\r\n":
            end += 1
        if end == pos or end - pos > 32:
            raise ImageHeaderError(f"the {what} header is malformed")
        tokens.append(head[pos:end])
        pos = end
    return tokens, start + pos


def _side(token: bytes, what: str) -> int:
    if not token.isdigit():
        raise ImageHeaderError(f"the {what} header has a non-numeric size {token[:20]!r}")
    return int(token)


def _ppm(data: memoryview) -> ImageInfo:
    (magic, width, height, _), _ = _tokens(data, 0, 4, "PPM")
    if magic != b"P6":
        raise ImageHeaderError("the PPM header must start with P6 (binary RGB)")
    return ImageInfo("ppm", _side(width, "PPM"), _side(height, "PPM"), 3)


def _pfm(data: memoryview) -> ImageInfo:
    (width, height, _), _ = _tokens(data, 2, 3, "PFM")
    return ImageInfo("pfm", _side(width, "PFM"), _side(height, "PFM"), 3 if data[1] == ord("F") else 1)


def _rgbe(data: memoryview) -> ImageInfo:
    """Radiance header lines up to the ``-Y height +X width`` resolution line (the only
    orientation Mitsuba reads); a FORMAT line is required, as in Mitsuba."""
    head = bytes(data[:_TEXT_HEADER_BYTES])
    recognized = False
    for line in head.split(b"\n")[1:-1]:
        if line.startswith((b"FORMAT=32-bit_rle_rgbe", b"FORMAT=32-bit_rle_xyze")):
            recognized = True
        words = line.split()
        if len(words) == 4 and words[0] == b"-Y" and words[2] == b"+X":
            if not recognized:
                raise ImageHeaderError("the RGBE header has no FORMAT line before its resolution")
            return ImageInfo("rgbe", _side(words[3], "RGBE"), _side(words[1], "RGBE"), 3)
    raise ImageHeaderError(f"the RGBE header has no '-Y <height> +X <width>' line in its first "
                           f"{_TEXT_HEADER_BYTES} bytes")


def _bmp(data: memoryview) -> ImageInfo:
    """Uncompressed BMP with a 40-byte BITMAPINFOHEADER, as Mitsuba reads it."""
    _need(data, 34, "BMP")
    header_size, width, height, planes, bpp, compression = struct.unpack_from("<IiiHHI", data, 14)
    if header_size != 40 or planes != 1 or compression != 0 or bpp not in (8, 16, 24, 32):
        raise ImageHeaderError("unsupported BMP variant (Mitsuba reads uncompressed 8/16/24/32-bit BMP files "
                               "with a 40-byte header)")
    return ImageInfo("bmp", width, abs(height), bpp // 8)


def _tga(data: memoryview) -> ImageInfo:
    """TGA v2 (detected by its footer): width and height are signed 16-bit fields."""
    width, height, bpp = struct.unpack_from("<hhB", data, 12)
    return ImageInfo("tga", width, height, max(bpp // 8, 1))


_READERS = (
    (b"\x89PNG\r\n\x1a\n", _png),
    (b"\xff\xd8", _jpeg),
    (b"\x76\x2f\x31\x01", _exr),
    (b"\x93NUMPY", _npy),
    (b"#?", _rgbe),
    (b"PF", _pfm),
    (b"Pf", _pfm),
    (b"P6", _ppm),
    (b"BM", _bmp),
)

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


def test_each_sensor_target_is_written_as_exr_beside_its_npy(mi, tmp_path):
    """``JobWriter.targets``: ``targets/target-<s>.exr`` decodes (Mitsuba's reader) to the very
    float32 values of ``target-<s>.npy``, HDR and negative values unclamped; a resume of a job begun
    without the ``.exr`` writes the missing file and leaves the others as they are."""
    from services.jobs.artifacts import JobWriter
    from services.jobs.state import JobStates
    from services.store.local import FolderStore

    rng = np.random.default_rng(3)
    images = {0: rng.uniform(0.0, 40.0, (6, 8, 3)), 2: rng.normal(0.0, 1.0, (5, 4, 3)).astype(np.float32)}
    writer = JobWriter(JobStates(FolderStore(tmp_path)), "job")
    writer.targets(images)
    folder = tmp_path / "job" / "targets"
    for sensor, image in images.items():
        npy = np.load(folder / f"target-{sensor}.npy")
        decoded, fmt = _decode(mi, (folder / f"target-{sensor}.exr").read_bytes())
        assert fmt == "RGB" and np.array_equal(decoded, npy)
        assert np.array_equal(decoded, np.asarray(image, np.float32))
        assert decoded.max() > 1.0 or decoded.min() < 0.0                     # what a PNG could not keep
        assert (folder / f"target-{sensor}.png").is_file()
    (folder / "target-2.exr").unlink()
    before = (folder / "target-2.npy").stat().st_mtime_ns
    writer.targets(images)
    assert np.array_equal(_decode(mi, (folder / "target-2.exr").read_bytes())[0], np.load(folder / "target-2.npy"))
    assert (folder / "target-2.npy").stat().st_mtime_ns == before

"""Primary rays of a sensor and the splatting of per-ray values into its film (Eq. 1, 3, 11).

Gradient images of every method are formed exactly as Mitsuba forms its images: the same
jittered pixel samples, the same reconstruction filter and the same weight normalisation of the
sensor's film (``film.create_block`` / ``put_block`` / ``develop``). Comparing an NDRF gradient
image with a ``prb`` one therefore compares estimators, not pixel filters.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import torch

from services.solver.jit_types import Float, Vector
from services.solver.sampling.delta import DeltaChain, trace_through_delta
from services.solver.sampling.tensors import floats, tensor

#: ``sample1`` of ``Sensor.sample_ray``: the wavelength sample (unused by RGB variants).
WAVELENGTH_SAMPLE: Float = 0.5


def _shutter(sensor: mi.Sensor) -> Float:
    """The time of every ray: the shutter's opening (a Python float, broadcast)."""
    return sensor.shutter_open()


@dataclass
class CameraSamples:
    """``K = W·H·spp`` primary rays, followed through delta surfaces.

    chain      the first non-delta interaction of each ray and the delta throughput
    weight     sensor importance weight of the ray (1 for the usual cameras)
    position   film position of each sample (``mi.Point2f``, pixel units)
    """

    chain: DeltaChain
    weight: mi.Spectrum
    position: mi.Point2f
    spp: int


def make_sampler(seed: int, lanes: int) -> mi.Sampler:
    """An independent sampler with ``lanes`` lanes. The seed is opaque: a new seed does not
    trigger a new kernel compilation (a literal would be baked into the kernel)."""
    sampler = mi.load_dict({"type": "independent", "sample_count": 1})
    sampler.seed(dr.opaque(mi.UInt32, seed), lanes)
    return sampler


def sample_camera(scene: mi.Scene, sensor: mi.Sensor, spp: int, seed: int,
                  delta_depth: int) -> tuple[CameraSamples, mi.Sampler]:
    """Jittered primary rays, ``spp`` per pixel, in Mitsuba's pixel-major order.

    Returns the samples and the sampler (which the caller keeps using for secondary rays).
    """
    film = sensor.film()
    width, height = (int(v) for v in film.crop_size())
    offset: Vector = mi.ScalarVector2i(film.crop_offset())
    lanes = width * height * spp
    sampler = make_sampler(seed, lanes)
    with dr.suspend_grad():
        index = dr.arange(mi.UInt32, lanes) // spp
        pixel = mi.Vector2i(mi.Int32(index % width), mi.Int32(index // width)) + offset
        jitter: Vector = sampler.next_2d()
        position = mi.Vector2f(pixel) + jitter
        film_uv = (position - mi.Vector2f(offset)) / mi.ScalarVector2f(width, height)
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
        ray, weight = sensor.sample_ray(_shutter(sensor), WAVELENGTH_SAMPLE, film_uv, aperture)
    chain = trace_through_delta(scene, ray, sampler, delta_depth, mi.Bool(True))
    splat = mi.Point2f(pixel) if film.rfilter().is_box_filter() else position
    return CameraSamples(chain, weight, splat, spp), sampler


def develop(sensor: mi.Sensor, samples: CameraSamples, values: torch.Tensor) -> torch.Tensor:
    """Splat per-ray values ``(K, C, 3)`` through the sensor's film: ``(C, H, W, 3)`` float32, on the
    solver's device (:func:`services.solver.sampling.tensors.to_host` for an image to write).

    With a box filter the film's weighted average is the plain mean of each pixel's ``spp``
    consecutive samples; it is computed here directly, which is deterministic (the film's
    parallel atomic accumulation is not bit-reproducible) and avoids one film pass per channel.
    Other filters go through the film itself, the values handed to it and the image taken back
    through DLPack (no copy through the host).
    """
    film = sensor.film()
    width, height = (int(v) for v in film.crop_size())
    channels = values.shape[1]
    if film.rfilter().is_box_filter():
        per_pixel = values.reshape(height, width, samples.spp, channels, 3).double().mean(2)
        return per_pixel.permute(2, 0, 1, 3).float().contiguous()
    has_alpha = mi.has_flag(film.flags(), mi.FilmFlags.Alpha)
    images = []
    for c in range(channels):
        film.prepare([])
        block = film.create_block()
        value: list[Float] = [floats(values[:, c, i]) for i in range(3)]
        block.put(samples.position, value + ([mi.Float(1.0)] if has_alpha else []) + [mi.Float(1.0)])
        film.put_block(block)
        images.append(tensor(film.develop())[..., :3])
    return torch.stack(images)   # (C, H, W, 3), in torch's memory: the views of the developed films end here


def camera_points(scene: mi.Scene, sensor: mi.Sensor, seed: int, count: int, delta_depth: int):
    """Up to ``count`` residual points where the camera looks: first non-delta hits of primary
    rays through uniformly random film positions, with ``ω_o`` towards the camera (``si.wi``).
    Rays that miss, or end on an emitter or a back face, are dropped. Returns the interactions
    and how many there are."""
    from services.solver.sampling.surface import queryable

    lanes = 2 * count
    sampler = make_sampler(seed, lanes)
    with dr.suspend_grad():
        aperture = sampler.next_2d() if sensor.needs_aperture_sample() else mi.Point2f(0.5)
        ray, _ = sensor.sample_ray(_shutter(sensor), WAVELENGTH_SAMPLE, sampler.next_2d(), aperture)
        chain = trace_through_delta(scene, ray, sampler, delta_depth, mi.Bool(True))
        valid = dr.compress(chain.active & queryable(chain.si, scene))
        kept = min(count, dr.width(valid))
        if kept == 0:
            return None, 0
        si = dr.gather(mi.SurfaceInteraction3f, chain.si, dr.gather(mi.UInt32, valid, dr.arange(mi.UInt32, kept)))
    return si, kept

"""Residual points ``(x_j, ω_o,j)`` with their density ``p(x, ω_o)`` (paper Eq. 8).

The residual domain is every shape whose BSDF has a non-delta (smooth) lobe and which is not an
emitter. Emitting surfaces are handled exactly (their emission is added where a ray hits them, and
their reflected radiance is not represented); purely specular surfaces are never residual points:
rays pass through them (:mod:`services.solver.sampling.delta`).

``x`` is uniform by area over the domain: pick a shape with probability ``A_s / A``, then a point
uniformly on it, so ``p(x) = 1 / A``. ``ω_o`` is uniform on the hemisphere of the normal
(``1 / 2π``), or on the whole sphere (``1 / 4π``) when the BSDF scatters on both sides.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from services.solver.jit_types import Color, MitsubaObject


def _smooth(flags) -> mi.Bool:
    return mi.has_flag(flags, mi.BSDFFlags.Smooth)


def two_sided(flags) -> mi.Bool:
    """Whether a BSDF (per lane) scatters light leaving its back side too."""
    return mi.has_flag(flags, mi.BSDFFlags.BackSide) | mi.has_flag(flags, mi.BSDFFlags.Transmission)


def pure_delta(flags) -> mi.Bool:
    """Ideal-specular only (mirror, smooth glass): rays continue through such a surface."""
    return mi.has_flag(flags, mi.BSDFFlags.Delta) & ~_smooth(flags)


def queryable(si: mi.SurfaceInteraction3f, scene: mi.Scene) -> mi.Bool:
    """Lanes where the neural fields are defined: a valid, non-emitting, smooth surface seen from
    a side that reflects light. One-sided BSDFs are black on their back side; the fields are
    never trained there, so querying them would return garbage instead of the correct zero."""
    flags = si.bsdf().flags()
    front = mi.Frame3f.cos_theta(si.wi) > 0
    return si.is_valid() & ~si.shape.is_emitter() & _smooth(flags) & (front | two_sided(flags))


def residual_shapes(scene: mi.Scene) -> list[int]:
    """Indices (into ``scene.shapes()``) of the shapes that make up the residual domain."""
    out = []
    for i, shape in enumerate(scene.shapes()):
        flags = shape.bsdf().flags() if shape.bsdf() is not None else 0
        smooth = bool(int(flags) & int(mi.BSDFFlags.Smooth))
        if smooth and not shape.is_emitter() and shape.surface_area()[0] > 0:
            out.append(i)
    return out


@dataclass
class ResidualPoints:
    """``B`` residual points: ``si.wi`` holds ``ω_o`` in the local frame; ``weight = p_ref / p``
    where ``p_ref = 1 / (2π A)``, so hemisphere lanes weigh 1 and sphere lanes 2 (Eq. 8)."""

    si: mi.SurfaceInteraction3f
    weight: mi.Float


class SurfaceSampler:
    """Samples ``(x, ω_o)`` over the residual domain of a scene."""

    def __init__(self, scene: mi.Scene):
        indices = residual_shapes(scene)
        if not indices:
            raise ValueError("the scene has no non-emitting surface with a smooth BSDF: nothing to learn")
        shapes = scene.shapes()
        areas = [float(shapes[i].surface_area()[0]) for i in indices]
        self.total_area = math.fsum(areas)
        self.distribution = mi.DiscreteDistribution(mi.Float(areas))
        self.shape_index = mi.UInt32(indices)
        self.scene = scene  # keeps the shapes alive: a ShapePtr does not own its shape
        self.shapes_dr = scene.shapes_dr()
        self.shape_ids = [shapes[i].id() for i in indices]

    def sample(self, sampler: mi.Sampler, count: int) -> ResidualPoints:
        """Draw ``count`` points; ``sampler`` must have been seeded with ``count`` lanes."""
        with dr.suspend_grad():
            slot = self.distribution.sample(sampler.next_1d())
            shape: MitsubaObject = dr.gather(mi.ShapePtr, self.shapes_dr, dr.gather(mi.UInt32, self.shape_index, slot))
            ps = shape.sample_position(0.0, sampler.next_2d())
            no_wavelengths: Color = dr.zeros(mi.Color0f)
            si = mi.SurfaceInteraction3f(ps, no_wavelengths)
            si.shape = shape
            both = two_sided(shape.bsdf().flags())
            u = sampler.next_2d()
            hemi = mi.warp.square_to_uniform_hemisphere(u)
            sphere = mi.warp.square_to_uniform_sphere(u)
            si.wi = dr.select(both, sphere, hemi)
            weight = dr.select(both, mi.Float(2.0), mi.Float(1.0))
        return ResidualPoints(si, weight)

    def density(self, points: ResidualPoints) -> mi.Float:
        """``p(x, ω_o)`` of the drawn points (for tests of Eq. 8)."""
        return 1.0 / (self.total_area * 2.0 * dr.pi * points.weight)

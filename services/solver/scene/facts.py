"""What a scene and its chosen parameters can produce, measured by a cheap Monte Carlo probe.

`choose_effects` (:mod:`services.solver.scene.effects`) is pure logic over these facts. The probe uses
the solver's own machinery, so what it reports is what the solver would compute:

* **interreflection**: of ``probe_rays`` BSDF-sampled rays leaving residual points, how many end
  on another surface of the residual domain (where the fields would be queried);
* **delta chains**: the distribution of ideal-specular chain lengths of camera rays and of those
  surface rays, followed up to ``max_delta_depth``;
* **reach of each optimized scalar**: camera paths are followed for ``probe_depth`` bounces; at
  every vertex the local derivatives ``∂emitted`` / ``∂throughput`` (forward-mode AD of
  ``bsdf.eval`` and ``emitter.eval``, Eq. 9) are computed per scalar. A scalar whose local
  derivatives vanish at every vertex of every probed path cannot change the image through paths
  of that length; the RGB channels in which a scalar's derivatives are non-zero tell which
  outputs of ``dL_theta`` it needs (RGB transport never mixes channels). A texture is probed as
  one unit, along the sum of its texels (one traversal, not one per texel; its facts and its plan
  entry stand for every texel).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from services.solver.jit_types import Bool, Float
from services.solver.sampling.camera import WAVELENGTH_SAMPLE, make_sampler, sample_camera
from services.solver.sampling.incident import evaluate_attached, evaluate_incident, sample_geometry, sample_incident
from services.solver.sampling.surface import SurfaceSampler, pure_delta, queryable, residual_shapes
from services.solver.sampling.tensors import rgb, to_host
from services.solver.scene.load import LoadedScene
from services.solver.scene.params import FORWARD_GROUP, ParameterSet
from services.solver.seeds import derive_seed


@dataclass(frozen=True)
class ScalarFacts:
    """What the probe saw of one optimized scalar: the largest |local derivative| per RGB channel,
    and the shortest camera path (in bounces from the camera hit) where it was non-zero."""

    label: str
    owner: str
    channel_magnitude: tuple[float, float, float]
    first_bounce: int | None
    #: scalars it stands for: 1, or a texture's (probed as one unit, along the sum of its texels)
    size: int = 1


@dataclass(frozen=True)
class SceneFacts:
    shapes: int
    emitters: int
    residual_shapes: int
    delta_shapes: list[str]
    probe_rays: int
    interreflection_hits: int
    delta_chain_counts: list[int]            # counts[d] = probed rays whose delta chain had length d
    delta_unfinished: int                    # probed rays still on a delta surface at the probe's cap
    probe_depth: int
    scalars: list[ScalarFacts] = field(default_factory=list)   # one per unit (ParameterSet.units)


def _delta_lengths(scene: mi.Scene, ray: mi.Ray3f, sampler: mi.Sampler, cap: int, active: Bool):
    """Length of the delta chain of each ray (``cap + 1`` for chains not finished by ``cap``)."""
    length = mi.UInt32(0)
    si = scene.ray_intersect(ray, active)
    on_delta = active & si.is_valid() & pure_delta(si.bsdf().flags())
    ctx = mi.BSDFContext()
    for _ in range(cap + 1):
        if not dr.any(on_delta):
            break
        length[on_delta] += 1
        bs, _ = si.bsdf().sample(ctx, si, sampler.next_1d(on_delta), sampler.next_2d(on_delta), on_delta)
        si_next = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), on_delta)
        si[on_delta] = si_next
        on_delta &= si.is_valid() & pure_delta(si.bsdf().flags())
        sampler.schedule_state()
        dr.eval(si, length, on_delta)          # keep each bounce's kernel small (see delta.py)
    lengths = np.array(length, dtype=np.int64)
    return lengths[np.broadcast_to(np.array(active, dtype=bool), lengths.shape)]


def probe_scene(scene: LoadedScene, parameters: ParameterSet, *, probe_rays: int = 1 << 15,
                probe_depth: int = 6, max_delta_depth: int = 64, seed: int = 0) -> SceneFacts:
    mi_scene = scene.scene
    shapes = mi_scene.shapes()
    delta = [s.id() for s in shapes if s.bsdf() is not None and bool(int(s.bsdf().flags()) & int(mi.BSDFFlags.Delta))
             and not int(s.bsdf().flags()) & int(mi.BSDFFlags.Smooth)]
    lengths: list[np.ndarray] = []

    # ------------------------------------------------ interreflection from residual points
    hits = 0
    if residual_shapes(mi_scene):
        surface = SurfaceSampler(mi_scene)
        points = surface.sample(make_sampler(derive_seed(seed, "probe", "points"), probe_rays), probe_rays)
        sampler = make_sampler(derive_seed(seed, "probe", "incident"), probe_rays)
        inc = sample_incident(mi_scene, points.si, sampler, delta_depth=max_delta_depth)
        hits = int(np.count_nonzero(np.array(inc.hit_surface)))
        bs, _ = points.si.bsdf().sample(mi.BSDFContext(), points.si, sampler.next_1d(), sampler.next_2d())
        if delta:
            lengths.append(_delta_lengths(mi_scene, points.si.spawn_ray(points.si.to_world(bs.wo)), sampler,
                                          max_delta_depth, bs.pdf > 0))

    # ------------------------------------------- camera paths: reach of every scalar
    width, height = scene.resolution()
    spp = max(1, probe_rays // max(1, width * height))
    samples, sampler = sample_camera(mi_scene, scene.sensor(0), spp, derive_seed(seed, "probe", "camera"), max_delta_depth)
    if delta:
        start: Float = 0.0
        camera_rays, _ = scene.sensor(0).sample_ray(start, WAVELENGTH_SAMPLE, sampler.next_2d(), mi.Point2f(0.5))
        lengths.append(_delta_lengths(mi_scene, camera_rays, sampler, max_delta_depth, mi.Bool(True)))
    magnitude, first = _camera_reach(mi_scene, samples, sampler, parameters, probe_depth, max_delta_depth)
    counts = np.bincount(np.concatenate(lengths), minlength=max_delta_depth + 2) if lengths else np.zeros(1, int)
    return SceneFacts(
        shapes=len(shapes), emitters=len(mi_scene.emitters()), residual_shapes=len(residual_shapes(mi_scene)),
        delta_shapes=delta, probe_rays=probe_rays, interreflection_hits=hits,
        delta_chain_counts=[int(c) for c in counts[:max_delta_depth + 1]],
        delta_unfinished=int(counts[max_delta_depth + 1:].sum()), probe_depth=probe_depth,
        scalars=[ScalarFacts(label, info_owner, (float(magnitude[i, 0]), float(magnitude[i, 1]), float(magnitude[i, 2])),
                             first[i], size)
                 for i, (label, info_owner, size) in enumerate(_owners(parameters))],
    )


def _camera_reach(mi_scene: mi.Scene, samples, sampler: mi.Sampler, parameters: ParameterSet, probe_depth: int,
                  max_delta_depth: int) -> tuple[np.ndarray, list[int | None]]:
    """Follow the camera paths of ``samples`` for ``probe_depth`` bounces with forward-mode
    derivatives along each unit of ``parameters.units()`` (a value's scalar, or a whole texture):
    the largest |derivative| of each unit per RGB channel ``(U, 3)``, and the bounce where each
    first changed a path (0: at the camera hit's own light)."""
    units = parameters.units()
    magnitude = np.zeros((len(units), 3))
    first: list[int | None] = [None] * len(units)
    # A graph that reads a bitmap is traversed at most FORWARD_GROUP times. Each group evaluates its
    # outputs under its own tracking: the last traversal clears the edges from a texture's data to
    # the texture that params.update() derived from it, which the next group needs again.
    group = FORWARD_GROUP if parameters.has_textures else max(1, len(units))

    def derivatives(outputs) -> list[list]:
        rows: list[list] = []
        for start in range(0, len(units), group):
            with parameters.tracking():
                rows += parameters.forward_units(outputs(), units[start:start + group])
        return rows

    si = samples.chain.si
    active = samples.chain.active
    with dr.suspend_grad():
        emitter = si.emitter(mi_scene, active)
        on_emitter = active & (emitter != None)

    def emitted():
        with dr.resume_grad(), dr.scoped_set_flag(dr.JitFlag.SymbolicCalls, False):
            return [dr.select(on_emitter, emitter.eval(si, on_emitter), 0.0)]

    _accumulate(magnitude, first, 0, derivatives(emitted))
    for bounce in range(probe_depth):
        where = active & queryable(si, mi_scene)
        if not dr.any(where):
            break
        geometry = sample_geometry(mi_scene, si, sampler, delta_depth=max_delta_depth, active=where)
        geometry.schedule()
        inc = evaluate_incident(mi_scene, geometry)   # the lanes the guard keeps go on
        _accumulate(magnitude, first, bounce,
                    derivatives(lambda geometry=geometry: list(evaluate_attached(mi_scene, geometry))))
        si, active = inc.hit, inc.hit_surface
        sampler.schedule_state()
        dr.eval(si, active)                    # one bounce per kernel
    return magnitude, first


def direct_reach(scene: LoadedScene, parameters: ParameterSet, *, probe_rays: int = 1 << 12, max_delta_depth: int = 8,
                 seed: int = 0) -> list[bool]:
    """Per optimized scalar: does it change the light leaving the first camera hits directly
    (a BSDF there, seen through at most ``max_delta_depth`` mirrors, or an emitter seen or lighting
    them)? False for a scalar that reaches the image only after a bounce off another surface (the
    hidden object of the paper's Fig. 5). One bounce of :func:`probe_scene`'s camera probe,
    ``probe_rays`` rays of the first sensor, at the parameters' current values."""
    width, height = scene.resolution()
    spp = max(1, probe_rays // max(1, width * height))
    samples, sampler = sample_camera(scene.scene, scene.sensor(0), spp, derive_seed(seed, "probe", "direct"),
                                     max_delta_depth)
    _, first = _camera_reach(scene.scene, samples, sampler, parameters, 1, max_delta_depth)
    return [first[u] == 0 for u, unit in enumerate(parameters.units()) for _ in unit]


def _owners(parameters: ParameterSet):
    """``(label, owner, size)`` per unit of ``parameters.units()`` (a texture: its key, its texels)."""
    kinds = parameters.owner_kinds()
    out = []
    for unit in parameters.units():
        key = parameters.scalars[unit[0]].key
        label = parameters.scalars[unit[0]].label if len(unit) == 1 and not _texture(parameters, key) else key
        out.append((label, kinds[key], len(unit)))
    return out


def _texture(parameters: ParameterSet, key: str) -> bool:
    return parameters.infos[parameters.keys.index(key)].texture


def _accumulate(magnitude: np.ndarray, first: list, bounce: int, per_scalar: list[list]) -> None:
    for i, grads in enumerate(per_scalar):
        peak = np.zeros(3)
        for g in grads:
            values = np.nan_to_num(np.abs(to_host(rgb(g))), nan=0.0, posinf=0.0)
            if values.size:
                peak = np.maximum(peak, values.max(0))
        magnitude[i] = np.maximum(magnitude[i], peak)
        if first[i] is None and peak.max() > 0:
            first[i] = bounce

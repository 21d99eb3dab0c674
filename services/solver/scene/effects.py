"""`choose_effects`: simulate only what a scene and its chosen parameters can produce.

Pure logic over :class:`services.solver.scene.facts.SceneFacts` (measured by a probe) and the job's
method and overrides. Every decision carries the reason a user reads in the job's plan.json:

* ``emission_term``      ∂E of Eq. 4, non-zero only for emitter parameters
* ``bsdf_term``          ∫ (∂f) L of Eq. 4, non-zero only for BSDF parameters
* ``differential_field`` dL_theta, needed only when light bounces between surfaces (otherwise the
                         one-bounce estimate with emission alone is exact)
* ``radiance_field``     L_phi, needed only for ∫ (∂f) L where the incident light includes
                         reflected light (BSDF parameters and interreflection)
* ``delta_depth``        ideal-specular bounces a ray must be followed through
* per scalar             dropped when no probed camera path is influenced by it (zero gradient,
                         said instead of trained); the RGB channels of dL_theta it needs (a
                         texture: one entry for all its texels)
"""

from __future__ import annotations

from collections.abc import Collection
from dataclasses import asdict, dataclass, field

from schemas.job import EffectOverrides
from services.solver.scene.facts import SceneFacts

#: A delta depth is enough when fewer than this fraction of probed rays needs more bounces.
DELTA_TAIL = 1e-4


@dataclass(frozen=True)
class EffectChoice:
    """One term or field of the chosen effects: on or off (or a depth), why, and whether the job forced it."""
    value: bool | int
    reason: str
    forced: bool = False


@dataclass(frozen=True)
class ScalarEffect:
    label: str
    active: bool
    channels: tuple[int, ...]
    reason: str
    #: Bounces from the camera hit to the first vertex where the scalar changed a probed path
    #: (0: seen directly; None: not reached or not probed).
    first_bounce: int | None = None
    #: scalars it stands for: 1, or a texture's texels (planned as one unit)
    size: int = 1


@dataclass(frozen=True)
class Effects:
    emission_term: EffectChoice
    bsdf_term: EffectChoice
    radiance_field: EffectChoice
    differential_field: EffectChoice
    delta_depth: EffectChoice
    scalars: list[ScalarEffect]
    warnings: list[str] = field(default_factory=list)

    @property
    def active_scalars(self) -> list[int]:
        """Indices into ``p`` of the active scalars (a texture's entry stands for its texels)."""
        return [i for i, _ in self.active_channels()]

    def active_channels(self) -> list[tuple[int, tuple[int, ...]]]:
        """``(index into p, RGB channels carried)`` of every active scalar."""
        out, offset = [], 0
        for s in self.scalars:
            if s.active:
                out += [(offset + k, s.channels) for k in range(s.size)]
            offset += s.size
        return out

    def to_json(self) -> dict:
        return asdict(self)


def _switch(name: str, setting: str, needed: bool, reason: str, warnings: list[str], consequence: str) -> EffectChoice:
    if setting == "auto":
        return EffectChoice(needed, reason)
    value = setting == "on"
    if needed and not value:
        warnings.append(f"{name} forced off although it is needed ({reason}): {consequence}")
    return EffectChoice(value, f"forced {setting} by the job ({'needed' if needed else 'not needed'}: {reason})", True)


def _delta_depth(facts: SceneFacts, cap: int) -> tuple[int, str]:
    if not facts.delta_shapes:
        return 0, "no ideal-specular surface in the scene"
    counts = list(facts.delta_chain_counts) + [facts.delta_unfinished]
    total = max(1, sum(counts))
    for depth in range(len(counts)):
        longer = sum(counts[depth + 1:])
        if longer / total < DELTA_TAIL:
            if depth <= cap:
                return depth, (f"{len(facts.delta_shapes)} ideal-specular shape(s); {total} probe rays: "
                               f"{longer} need more than {depth} delta bounce(s)")
            break
    return cap, (f"{len(facts.delta_shapes)} ideal-specular shape(s); chains longer than the cap of {cap} "
                 f"remain ({sum(counts[cap + 1:])} of {total} probe rays are cut)")


def choose_effects(facts: SceneFacts, method: str, uses: Collection[str], overrides: EffectOverrides | None = None,
                 max_delta_depth: int = 8) -> Effects:
    """The effects for ``method``, which can use the fields named in ``uses`` (``"radiance"``,
    ``"differential"``: the method class's ``uses``, from the registry of
    ``services.solver.estimators.methods``)."""
    overrides = overrides or EffectOverrides()
    warnings: list[str] = []

    scalars = []
    for s in facts.scalars:
        reached = max(s.channel_magnitude) > 0
        if not reached and overrides.drop_unreachable:
            scalars.append(ScalarEffect(s.label, False, (), f"no camera path of up to {facts.probe_depth + 1} bounces "
                                                          f"depends on it: its gradient is zero", s.first_bounce,
                                      s.size))
            continue
        channels = tuple(c for c in range(3) if s.channel_magnitude[c] > 0) if overrides.merge_channels and reached \
            else (0, 1, 2)
        where = "seen directly" if s.first_bounce == 0 else (
            f"first reaches the image after {s.first_bounce} bounce(s)" if s.first_bounce is not None else "not probed")
        scalars.append(ScalarEffect(s.label, True, channels, f"{s.owner} parameter, {where}; "
                                                           f"changes channel(s) {', '.join('RGB'[c] for c in channels)}",
                                  s.first_bounce, s.size))
    active = [s for s, p in zip(facts.scalars, scalars) if p.active]
    if facts.scalars and not active:
        warnings.append("no optimized scalar can change the image: every gradient is zero")

    emitters = sum(s.size for s in active if s.owner == "emitter")
    bsdfs = sum(s.size for s in active if s.owner == "bsdf")
    emission = _switch("emission_term", overrides.emission_term, emitters > 0,
                       f"{emitters} emitter scalar(s) optimized" if emitters else "no emitter parameter: ∂E = 0",
                       warnings, "the derivative of emission is dropped")
    bsdf = _switch("bsdf_term", overrides.bsdf_term, bsdfs > 0,
                   f"{bsdfs} BSDF scalar(s) optimized" if bsdfs else "no BSDF parameter: ∂f = 0",
                   warnings, "the derivative of the BSDFs is dropped")

    bounces = facts.interreflection_hits > 0
    bounce_text = (f"{facts.interreflection_hits} of {facts.probe_rays} probe rays from surfaces reach another surface"
                   if bounces else f"none of {facts.probe_rays} probe rays from surfaces reaches another surface: "
                                   f"one bounce with emission alone is exact")
    if "differential" not in uses:
        differential_reason, differential_needed = f"{method} does not use dL_theta", False
    elif not active:
        differential_reason, differential_needed = "no scalar to differentiate", False
    else:
        differential_reason, differential_needed = bounce_text, bounces
    differential = _switch("differential_field", overrides.differential_field, differential_needed,
                           differential_reason, warnings, "indirect gradients are missed (as by a radiance cache)")

    if "radiance" not in uses:
        radiance_reason, radiance_needed = f"{method} does not use L_phi", False
    elif not bsdf.value:
        radiance_reason, radiance_needed = "the term ∫ (∂f) L vanishes without BSDF parameters", False
    else:
        radiance_reason, radiance_needed = (f"∫ (∂f) L needs the reflected light: {bounce_text}" if bounces
                                            else bounce_text), bounces
    radiance = _switch("radiance_field", overrides.radiance_field, radiance_needed, radiance_reason, warnings,
                       "∫ (∂f) L sees emitted light only")

    depth, depth_reason = _delta_depth(facts, max_delta_depth)
    if overrides.delta_depth is not None:
        if overrides.delta_depth < depth:
            warnings.append(f"delta_depth forced to {overrides.delta_depth}, the scene needs {depth}: "
                            f"light through longer mirror/glass chains is cut")
        delta = EffectChoice(overrides.delta_depth, f"forced by the job (choose_effects: {depth}; {depth_reason})", True)
    else:
        delta = EffectChoice(depth, depth_reason)
    return Effects(emission, bsdf, radiance, differential, delta, scalars, warnings)

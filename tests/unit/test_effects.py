"""`choose_effects` as pure logic: for each decision, facts where it applies."""

from __future__ import annotations

import pytest

from schemas.job import EffectOverrides
from schemas.methods import Method
from services.solver.estimators.methods import method_class
from services.solver.scene.effects import choose_effects as choose_for
from services.solver.scene.facts import ScalarFacts, SceneFacts


def choose_effects(facts, method, overrides=None, **options):
    """The effects for a method, with the fields the registry says it can use."""
    return choose_for(facts, method, method_class(method).uses, overrides, **options)


def facts(*scalars, hits=1000, delta=(), counts=(65536,), unfinished=0):
    return SceneFacts(shapes=8, emitters=1, residual_shapes=7, delta_shapes=list(delta), probe_rays=4096,
                      interreflection_hits=hits, delta_chain_counts=list(counts), delta_unfinished=unfinished,
                      probe_depth=6, scalars=list(scalars))


def albedo(channel, first=0):
    magnitude = [0.0, 0.0, 0.0]
    magnitude[channel] = 0.3
    return ScalarFacts(f"wall[{channel}]", "bsdf", tuple(magnitude), first)


def radiance(channel):
    magnitude = [0.0, 0.0, 0.0]
    magnitude[channel] = 2.0
    return ScalarFacts(f"light[{channel}]", "emitter", tuple(magnitude), 0)


ROUGHNESS = ScalarFacts("roughness", "bsdf", (0.1, 0.2, 0.3), 0)
UNREACHABLE = ScalarFacts("closet[0]", "bsdf", (0.0, 0.0, 0.0), None)


def test_bsdf_parameters_with_interreflection_need_everything():
    effects = choose_effects(facts(albedo(0), albedo(1)), "ndrf-rhs")
    assert effects.bsdf_term.value and not effects.emission_term.value
    assert effects.radiance_field.value and effects.differential_field.value
    assert [s.channels for s in effects.scalars] == [(0,), (1,)]


def test_emitter_parameters_need_no_radiance_field():
    effects = choose_effects(facts(radiance(0), radiance(2)), "ndrf-lhs")
    assert effects.emission_term.value and not effects.bsdf_term.value
    assert not effects.radiance_field.value and "vanishes" in effects.radiance_field.reason
    assert effects.differential_field.value


def test_without_interreflection_one_bounce_is_exact():
    effects = choose_effects(facts(albedo(0), hits=0), "ndrf-lhs")
    assert not effects.differential_field.value and not effects.radiance_field.value
    assert "exact" in effects.differential_field.reason


EXPECTED_FIELDS = {Method.NDRF_LHS: (True, True), Method.NDRF_RHS: (True, True), Method.RADIANCE_CACHE: (True, False),
                   Method.DIRECT: (False, False), Method.PRB: (False, False),
                   Method.PRB_PROJECTIVE: (False, False), Method.DIRECT_PROJECTIVE: (False, False)}


@pytest.mark.parametrize("method", list(Method))
def test_fields_only_for_methods_that_use_them(method):
    effects = choose_effects(facts(albedo(0)), method)
    assert (effects.radiance_field.value, effects.differential_field.value) == EXPECTED_FIELDS[method]


def test_unreachable_scalars_are_dropped_with_a_reason():
    effects = choose_effects(facts(albedo(0), UNREACHABLE), "ndrf-rhs")
    assert [s.active for s in effects.scalars] == [True, False]
    assert "gradient is zero" in effects.scalars[1].reason
    kept = choose_effects(facts(albedo(0), UNREACHABLE), "ndrf-rhs", EffectOverrides(drop_unreachable=False))
    assert kept.scalars[1].active and kept.scalars[1].channels == (0, 1, 2)


def test_only_unreachable_scalars_warn_and_train_nothing():
    effects = choose_effects(facts(UNREACHABLE), "ndrf-rhs")
    assert not effects.differential_field.value and not effects.radiance_field.value
    assert any("every gradient is zero" in w for w in effects.warnings)


def test_channels_merge_for_rgb_components_not_for_a_roughness():
    effects = choose_effects(facts(albedo(2), ROUGHNESS), "ndrf-lhs")
    assert [s.channels for s in effects.scalars] == [(2,), (0, 1, 2)]
    unmerged = choose_effects(facts(albedo(2)), "ndrf-lhs", EffectOverrides(merge_channels=False))
    assert unmerged.scalars[0].channels == (0, 1, 2)


@pytest.mark.parametrize("delta, counts, unfinished, cap, expected", [
    ((), (65536,), 0, 8, 0),                         # no mirror: no delta bounce at all
    (("mirror",), (50000, 15536), 0, 8, 1),          # one planar mirror: one bounce
    (("m1", "m2"), (40000, 20000, 5000, 536), 0, 8, 3),
    (("m1", "m2"), (40000, 20000, 5000, 536), 9, 2, 2),   # facing mirrors beyond the cap
])
def test_delta_depth_is_what_the_probe_needs(delta, counts, unfinished, cap, expected):
    effects = choose_effects(facts(albedo(0), delta=delta, counts=counts, unfinished=unfinished), "ndrf-rhs",
                        max_delta_depth=cap)
    assert effects.delta_depth.value == expected


def test_forcing_off_a_needed_effect_warns_and_forcing_on_is_recorded():
    effects = choose_effects(facts(albedo(0)), "ndrf-rhs", EffectOverrides(differential_field="off", delta_depth=0))
    assert not effects.differential_field.value and effects.differential_field.forced
    assert any("differential_field forced off although it is needed" in w for w in effects.warnings)
    on = choose_effects(facts(albedo(0), hits=0), "ndrf-rhs", EffectOverrides(differential_field="on"))
    assert on.differential_field.value and on.differential_field.forced and not on.warnings
    assert "not needed" in on.differential_field.reason
    shallow = choose_effects(facts(albedo(0), delta=("mirror",), counts=(50000, 15536)), "ndrf-rhs",
                           EffectOverrides(delta_depth=0))
    assert shallow.delta_depth.value == 0 and any("delta_depth forced" in w for w in shallow.warnings)


def test_plan_serialises_with_every_reason():
    effects = choose_effects(facts(albedo(0), UNREACHABLE), "ndrf-lhs").to_json()
    for key in ("emission_term", "bsdf_term", "radiance_field", "differential_field", "delta_depth"):
        assert effects[key]["reason"]
    assert all(s["reason"] for s in effects["scalars"])

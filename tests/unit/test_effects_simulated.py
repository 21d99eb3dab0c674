"""The solver does what the chosen effects says: turning off what the effects calls unneeded leaves the
gradients unchanged; turning off what it calls needed changes them. (What the skipped work saves
in time is measured in bench/, not asserted here.)"""

from __future__ import annotations

import numpy as np
import pytest

from schemas.job import EffectOverrides
from schemas.solver import TrainingConfig
from services.solver.estimators.render import PathDepth

SMALL = TrainingConfig(residual_points=1024, incident_samples=4)


def gradient(mi, scene_dict_or_name, keys, method, overrides=None, steps=0, resolution=(24, 24), spp=8):
    """Plan (with overrides), train what the effects asks for, and return (effects, images)."""
    from services.solver.estimators.methods import make_method, method_class
    from services.solver.estimators.problem import Problem
    from services.solver.scene.effects import choose_effects
    from services.solver.scene.facts import probe_scene
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.training.trainer import fields_of, trainer_for

    scene = (load_scene(builtin=scene_dict_or_name, resolution=resolution) if isinstance(scene_dict_or_name, str)
             else load_scene(mitsuba_dict=scene_dict_or_name, resolution=resolution))
    problem = Problem(scene, ParameterSet(scene.params, keys))
    effects = choose_effects(probe_scene(scene, problem.parameters, seed=1), method, method_class(method).uses,
                        overrides or EffectOverrides())
    problem.simulate(effects)
    estimator = make_method(method, effects)
    trainer = trainer_for(problem, estimator, SMALL, seed=0)
    if trainer is not None:
        trainer.train(steps)
    return effects, trainer, estimator.gradient_images(problem, fields_of(trainer), spp=spp, seed=5)


def test_no_interreflection_one_bounce_equals_forcing_both_fields_on(mi):
    from tests.support.scenes import sky_plane

    effects, trainer, planned = gradient(mi, sky_plane(), ["plane-bsdf.reflectance.value"], "ndrf-rhs")
    assert trainer is None and not effects.differential_field.value
    _, forced_trainer, forced = gradient(mi, sky_plane(), ["plane-bsdf.reflectance.value"], "ndrf-rhs",
                                         EffectOverrides(radiance_field="on", differential_field="on"), steps=5)
    assert forced_trainer.radiance is not None and forced_trainer.differential is not None
    np.testing.assert_allclose(planned, forced, atol=1e-7)          # the fields are never queried here


def test_emitter_parameters_skip_the_radiance_field_and_the_bsdf_term(mi):
    keys = ["light.emitter.radiance.value"]
    effects, trainer, planned = gradient(mi, "cornell-box", keys, "ndrf-lhs", steps=20)
    assert trainer.radiance is None and not effects.bsdf_term.value
    _, forced_trainer, forced = gradient(mi, "cornell-box", keys, "ndrf-lhs",
                                         EffectOverrides(radiance_field="on", bsdf_term="on"), steps=20)
    assert forced_trainer.radiance is not None
    np.testing.assert_allclose(planned, forced, rtol=1e-4, atol=1e-6)


def test_the_emission_term_is_skipped_exactly_when_no_emitter_parameter_is_optimized(mi):
    bsdf = ["red.reflectance.value"]
    effects, _, planned = gradient(mi, "cornell-box", bsdf, "direct")
    assert not effects.emission_term.value                                   # the decision itself
    _, _, forced = gradient(mi, "cornell-box", bsdf, "direct", EffectOverrides(emission_term="on"))
    np.testing.assert_allclose(planned, forced, atol=1e-7)                # skipping it loses nothing
    emitter = ["light.emitter.radiance.value"]
    effects, _, needed = gradient(mi, "cornell-box", emitter, "direct")
    assert effects.emission_term.value
    _, _, dropped = gradient(mi, "cornell-box", emitter, "direct", EffectOverrides(emission_term="off"))
    assert np.abs(needed).sum() > 0 and np.all(dropped == 0)              # where it is needed, it is everything


def test_delta_depth_beyond_what_is_needed_changes_nothing_below_it_does(mi):
    keys = ["sphere.reflectance.value"]
    effects, _, planned = gradient(mi, "mirror-box", keys, "direct")
    assert effects.delta_depth.value == 1
    _, _, deeper = gradient(mi, "mirror-box", keys, "direct", EffectOverrides(delta_depth=8))
    np.testing.assert_allclose(planned, deeper, atol=1e-7)
    shallow_plan, _, shallow = gradient(mi, "mirror-box", keys, "direct", EffectOverrides(delta_depth=0))
    assert shallow_plan.warnings
    assert np.abs(shallow - planned).sum() > 0.1 * np.abs(planned).sum()   # the sphere in the mirror is gone


@pytest.mark.slow
def test_forcing_off_the_needed_differential_field_loses_indirect_gradients(mi):
    """Without dL_theta, ndrf-rhs *is* a radiance cache (same samples, same L_phi): the indirect
    gradient the effects keeps is exactly what is lost."""
    keys = ["red.reflectance.value"]
    _, _, planned = gradient(mi, "cornell-box", keys, "ndrf-rhs", steps=60)
    effects, _, forced = gradient(mi, "cornell-box", keys, "ndrf-rhs", EffectOverrides(differential_field="off"), steps=60)
    _, _, cache = gradient(mi, "cornell-box", keys, "radiance-cache", steps=60)
    assert any("differential_field forced off" in w for w in effects.warnings)
    np.testing.assert_allclose(forced, cache, rtol=1e-5, atol=1e-7)   # up to JIT rounding
    assert np.linalg.norm(planned - cache) > 0.1 * np.linalg.norm(planned)


def test_unreachable_parameter_is_dropped_and_really_has_zero_gradient(mi):
    from services.solver.estimators.methods import Fields, make_method
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    keys = ["red.reflectance.value", "hidden-paint.reflectance.value"]
    effects, trainer, planned = gradient(mi, "closet-box", keys, "ndrf-lhs", steps=5)
    assert [s.active for s in effects.scalars] == [True] * 3 + [False] * 3
    assert trainer.differential.channels == 3                      # one channel per red-wall scalar
    assert np.all(planned[3:] == 0)
    scene = load_scene(builtin="closet-box", resolution=(24, 24))
    reference = make_method("prb", None, PathDepth(12, None)).gradient_images(
        Problem(scene, ParameterSet(scene.params, keys)), Fields(), spp=64, seed=3)
    assert np.all(reference[3:] == 0) and np.abs(reference[:3]).sum() > 0


@pytest.mark.slow
def test_merged_channels_carry_the_same_gradient(mi):
    keys = ["red.reflectance.value"]
    _, merged_trainer, merged = gradient(mi, "cornell-box", keys, "ndrf-lhs", steps=100)
    _, full_trainer, full = gradient(mi, "cornell-box", keys, "ndrf-lhs", EffectOverrides(merge_channels=False),
                                     steps=100)
    assert merged_trainer.differential.channels == 3 and full_trainer.differential.channels == 9
    for p in range(3):
        others = [c for c in range(3) if c != p]
        assert np.all(merged[p][..., others] == 0)                  # structurally zero, not learned
        assert np.abs(full[p][..., others]).max() < 0.1 * np.abs(full[p][..., p]).max()
        relative = np.linalg.norm(merged[p][..., p] - full[p][..., p]) / np.linalg.norm(full[p][..., p])
        assert relative < 0.25, relative


def test_direct_reach_tells_a_hidden_scalar_from_one_the_camera_sees(mi):
    from services.solver.scene.facts import direct_reach
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="hidden-object", resolution=(32, 32))
    parameters = ParameterSet(scene.params, ["hidden.reflectance.value", "walls.reflectance.value"])
    assert direct_reach(scene, parameters, probe_rays=1024) == [False] * 3 + [True] * 3

"""The method registry and the two entry points every method has: ``loss_gradient`` (every
iteration) must equal ``images`` contracted with dz/dy (Eq. 10) for the same samples."""

from __future__ import annotations

import numpy as np
import pytest

from schemas.methods import Method
from services.solver.estimators.render import PathDepth


def test_every_public_method_has_a_class_declaring_its_name_and_fields():
    from services.solver.estimators.methods import METHODS, method_class

    assert set(METHODS) == set(Method)
    for name, cls in METHODS.items():
        assert cls.name == name and cls.uses <= {"radiance", "differential"}
    with pytest.raises(ValueError, match="unknown gradient method 'nope'"):
        method_class("nope")


@pytest.fixture(scope="module")
def setting(mi):
    from schemas.solver import TrainingConfig
    from services.solver.estimators.methods import method_class
    from services.solver.estimators.problem import Problem
    from services.solver.scene.effects import choose_effects
    from services.solver.scene.facts import probe_scene
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.training.trainer import FieldTrainer

    scene = load_scene(builtin="cornell-box", resolution=(12, 10))
    problem = Problem(scene, ParameterSet(scene.params, ["red.reflectance.value", "light.emitter.radiance.value"]))
    problem.simulate(choose_effects(probe_scene(scene, problem.parameters, seed=1), "ndrf-rhs",
                                    method_class("ndrf-rhs").uses))
    trainer = FieldTrainer(problem, TrainingConfig(residual_points=512, incident_samples=4), radiance=True,
                           differential=True, seed=0)
    trainer.train(5)
    dz_dy = np.random.default_rng(0).normal(size=(10, 12, 3)).astype(np.float32)
    return problem, trainer, dz_dy


@pytest.mark.parametrize("name", list(Method))
def test_loss_gradient_is_the_contraction_of_the_images(setting, name):
    from services.solver.estimators.methods import contract, make_method
    from services.solver.training.trainer import fields_of

    problem, trainer, dz_dy = setting
    method = make_method(name, problem.effects, PathDepth(6, None))
    fields = fields_of(trainer)
    direct = method.loss_gradient(problem, fields, dz_dy, spp=3, seed=11)
    contracted = contract(method.gradient_images(problem, fields, spp=3, seed=11), dz_dy)
    assert direct.shape == (problem.parameters.n,) and np.abs(contracted).max() > 0
    np.testing.assert_allclose(direct, contracted, rtol=2e-4, atol=1e-6 * np.abs(contracted).max())


def test_a_plan_without_the_differential_field_makes_ndrf_lhs_a_one_bounce_estimate(setting):
    from dataclasses import replace

    from services.solver.estimators.methods import OneBounce, make_method
    from services.solver.scene.effects import EffectChoice

    problem, _, _ = setting
    effects = replace(problem.effects, differential_field=EffectChoice(False, "test"))
    method = make_method("ndrf-lhs", effects)
    assert isinstance(method, OneBounce) and method.name == Method.NDRF_LHS and not method.needs_differential


def test_prb_fused_step_agrees_with_separate_candidate_and_adjoint_passes(setting):
    """``prb`` renders the candidate and the adjoint in one differentiable render (independent
    seeds for the two passes); at 2048 spp it agrees with a separate path-traced candidate and
    adjoint pass to the Monte Carlo noise (5% allowed)."""
    from services.solver.estimators.losses import image_loss
    from services.solver.estimators.methods import GradientMethod, make_method
    from services.solver.estimators.render import render

    problem, _, _ = setting
    target = render(problem, spp=512, seed=99, depth=PathDepth(6, None)) * 1.3       # a target brighter than the scene
    loss = lambda y: image_loss("l2", y, target)
    prb = make_method("prb", problem.effects, PathDepth(6, None))
    fused = prb.candidate_and_gradient(problem, None, loss, spp=2048, gradient_spp=2048, seed=3, depth=PathDepth(6, None))
    separate = GradientMethod.candidate_and_gradient(prb, problem, None, loss, spp=2048, gradient_spp=2048, seed=4,
                                                     depth=PathDepth(6, None))
    print("fused", fused[0].mean(), fused[1], fused[2], "separate", separate[0].mean(), separate[1], separate[2])
    np.testing.assert_allclose(fused[0].mean(), separate[0].mean(), rtol=0.05)
    assert fused[1] == pytest.approx(separate[1], rel=0.05)
    np.testing.assert_allclose(fused[2], separate[2], rtol=0.05, atol=0.05 * np.abs(separate[2]).max())


def test_prb_gradient_images_of_a_texture_parameter(mi):
    """Forward mode through a bitmap (a derived value): per-texel images are non-zero, and their
    contraction equals the adjoint pass for the same samples."""
    from services.solver.estimators.methods import Fields, contract, make_method
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from tests.support.scenes import poster_box

    scene = load_scene(mitsuba_dict=poster_box(), resolution=(12, 10))
    problem = Problem(scene, ParameterSet(scene.params, ["back.bsdf.reflectance.data"]))
    prb = make_method("prb", None, PathDepth(4, None))
    dz_dy = np.random.default_rng(1).normal(size=(10, 12, 3)).astype(np.float32)
    images = prb.gradient_images(problem, Fields(), spp=8, seed=2)
    assert images.shape == (6, 10, 12, 3) and np.all(np.abs(images).reshape(6, -1).sum(1) > 0)
    np.testing.assert_allclose(prb.loss_gradient(problem, Fields(), dz_dy, spp=8, seed=2), contract(images, dz_dy),
                               rtol=1e-3, atol=1e-5 * np.abs(contract(images, dz_dy)).max())

"""Residual training reaches the exact solution where it is known.

A diffuse plane under a constant sky reflects L_r = ρ (per channel) everywhere, with ∂L_r/∂ρ = I.
Both fields must learn these constants to 5% within 150 steps (N = 1024, M = 8), with and without
the residual pool."""

from __future__ import annotations

import numpy as np
import pytest
import torch


@pytest.mark.parametrize("pooled", [True, False])
def test_fields_learn_the_exact_solution_of_a_sky_lit_plane(mi, pooled):
    """Pooled (both fields on one reused batch) and fresh (two new batches per step) alike."""
    from schemas.solver import PoolConfig, TrainingConfig
    from services.solver.estimators.problem import Problem
    from services.solver.sampling.camera import make_sampler
    from services.solver.sampling.tensors import field_query
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.training.trainer import FieldTrainer
    from tests.support.scenes import sky_plane

    albedo = np.array([0.2, 0.5, 0.8])
    scene = load_scene(mitsuba_dict=sky_plane(albedo))
    problem = Problem(scene, ParameterSet(scene.params, ["plane-bsdf.reflectance.value"]))
    config = TrainingConfig(residual_points=1024, incident_samples=8, learning_rate=1e-2,
                            pool=PoolConfig(enabled=pooled, chunks=4, reuse=4))
    trainer = FieldTrainer(problem, config, radiance=True, differential=True, seed=0)
    first = trainer.step()
    trainer.train(150)
    assert trainer.last.radiance_loss < 0.2 * first.radiance_loss

    query = field_query(problem.surface.sample(make_sampler(99, 2000), 2000).si)
    queried = trainer.queried()                                 # the weight averages the methods read
    for radiance, differential in ((trainer.radiance, trainer.differential), (queried.radiance, queried.differential)):
        with torch.no_grad():
            l_r = radiance(query).mean(0).numpy()
            d_l = problem.layout.unpack(differential(query)).mean(0).numpy()    # (3 scalars, 3 channels)
        assert l_r == pytest.approx(albedo, rel=0.05)
        assert d_l == pytest.approx(np.eye(3), abs=0.05)
    assert queried.radiance is not trainer.radiance


def test_a_method_without_its_field_refuses_to_run(mi):
    from services.solver.estimators.methods import Fields, make_method

    with pytest.raises(ValueError, match="needs a trained"):
        make_method("ndrf-lhs").gradient_images(None, Fields(), spp=1, seed=0)

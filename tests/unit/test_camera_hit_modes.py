"""The camera-hit methods' one estimate in its three modes (``CameraHitMethod.sample``): the forward
mode (``dI/dp`` per ray) equals central finite differences of the primal mode (``I`` per ray) with
the same samples, and the backward mode (``dz/dp`` for per-ray adjoint weights) equals the forward
mode contracted with those weights.

The scene: the textured Cornell box (a box pixel filter), 8 x 8, 2 spp, with the red wall's albedo
and the light's radiance optimized (6 scalars: ``∂f`` through the bounce and ``∂E`` at the camera
hits both count). Sampling is detached and the densities and MIS weights of a diffuse BSDF and an
area light do not depend on an albedo or a radiance, so with fixed samples the primal estimate is
linear in each scalar: a central difference is its derivative up to float32 rounding (measured:
about 1e-6 of the largest entry), whatever the step. The fields are untrained (arbitrary but fixed
values: ``T · L_phi(x')`` and the ``dL_theta`` terms are non-zero, which is all the check needs).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

KEYS = ["red.reflectance.value", "light.emitter.radiance.value"]
FILM, SPP, SEED = 8, 2, 5


@pytest.fixture(scope="module")
def setting(mi):
    from schemas.solver import FieldConfig
    from services.solver.estimators.layout import DerivativeLayout
    from services.solver.estimators.methods import Fields
    from services.solver.estimators.problem import Problem
    from services.solver.fields.field import NeuralField
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.scene.textured import textured_box

    scene = load_scene(mitsuba_dict=textured_box(size=4, views=1, film=FILM))
    problem = Problem(scene, ParameterSet(scene.params, KEYS))
    problem.layout = DerivativeLayout.by_component([3, 3])
    lo, hi = problem.bbox
    torch.manual_seed(0)
    fields = Fields(NeuralField(FieldConfig(), 3, lo, hi), NeuralField(FieldConfig(), problem.layout.outputs, lo, hi))
    return problem, fields


def _method(name):
    from services.solver.estimators.methods import make_method

    return make_method(name)


@pytest.mark.parametrize("name", ["direct", "radiance-cache"])
def test_the_forward_mode_is_the_derivative_of_the_primal(setting, name):
    import drjit as dr

    problem, fields = setting
    method, params, sensor = _method(name), problem.parameters, problem.scene.sensor(0)
    p0 = params.values()
    derivative = method.sample(dr.ADMode.Forward, problem, method.trace(problem, fields, sensor, SPP, SEED))

    def primal(values: np.ndarray) -> np.ndarray:
        params.assign(values)
        try:
            return method.sample(dr.ADMode.Primal, problem, method.trace(problem, fields, sensor, SPP, SEED,
                                                                         primal=True))[:, 0]
        finally:
            params.assign(p0)

    step = 0.05
    differences = np.stack([(primal(p0 + step * e) - primal(p0 - step * e)) / (2 * step) for e in np.eye(params.n)], 1)
    assert derivative.shape == differences.shape == (FILM * FILM * SPP, params.n, 3)
    scale = np.abs(differences).max()
    for i in range(params.n):                      # every scalar reaches some ray: the check is not vacuous
        assert np.abs(differences[:, i]).max() > 1e-3 * scale
    np.testing.assert_allclose(derivative, differences, rtol=1e-3, atol=1e-4 * scale)


@pytest.mark.parametrize("name", ["direct", "radiance-cache", "ndrf-rhs", "ndrf-lhs"])
def test_the_backward_mode_is_the_forward_mode_contracted(setting, name):
    """``dz/dp`` of ``z = Σ_rays δ · I`` (``δ`` random, signs mixed) by one reverse-mode pass plus the
    ``dL_theta`` terms contracted, against ``Σ_rays δ · dI/dp`` of the forward mode: one estimate in
    two AD modes (float32 sums in another order)."""
    import drjit as dr

    problem, fields = setting
    method, sensor = _method(name), problem.scene.sensor(0)
    rays = FILM * FILM * SPP
    delta = torch.from_numpy(np.random.default_rng(1).uniform(-1.0, 1.0, (rays, 3)).astype(np.float32))
    derivative = method.sample(dr.ADMode.Forward, problem, method.trace(problem, fields, sensor, SPP, SEED))
    pass_ = method.trace(problem, fields, sensor, SPP, SEED)
    adjoint = method.sample(dr.ADMode.Backward, problem, pass_, delta * pass_.scale).cpu().numpy()
    contracted = np.einsum("kc,kac->a", delta.double().numpy(), derivative.double().cpu().numpy())
    scale = np.abs(contracted).max()
    assert scale > 0 and adjoint.shape == (problem.parameters.n,)
    np.testing.assert_allclose(adjoint, contracted, rtol=1e-4, atol=1e-5 * scale)


def test_the_primal_of_ndrf_lhs_needs_the_radiance_field(setting):
    from services.solver.estimators.methods import Fields

    problem, fields = setting
    method = _method("ndrf-lhs")
    with pytest.raises(ValueError, match="needs a trained radiance field"):
        method.trace(problem, Fields(None, fields.differential), problem.scene.sensor(0), SPP, SEED, primal=True)

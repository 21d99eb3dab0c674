"""Sampling pdfs (Eq. 8, 9): integrate known functions over the scene's surfaces and directions.

Tolerances: Monte Carlo with 2^18..2^20 samples; the relative standard error of each estimate is
below 0.3%, the tolerances are 1% (area integrals) and 1.5% (incident integrals).
"""

from __future__ import annotations

import math

import numpy as np
import pytest


def _load(mi, scene_dict):
    from services.solver.scene.load import load_scene

    return load_scene(mitsuba_dict=scene_dict)


def test_residual_domain_excludes_emitters_and_mirrors(mi):
    from services.solver.sampling.surface import SurfaceSampler
    from tests.support.scenes import area_probe

    sampler = SurfaceSampler(_load(mi, area_probe()).scene)
    assert sorted(sampler.shape_ids) == ["ball", "floor"]
    assert sampler.total_area == pytest.approx(4.0 + 4 * math.pi * 0.25 ** 2, rel=1e-5)


def test_area_sampling_integrates_height_and_cosine_exactly(mi):
    """∫_M ∫_H y dω dA = 2π ∫_M y dA and ∫_M ∫_H cos θ dω dA = π A, estimated with the
    sampler's own pdf p(x, ω_o)."""
    import drjit as dr

    from services.solver.sampling.camera import make_sampler
    from services.solver.sampling.surface import SurfaceSampler
    from tests.support.scenes import area_probe

    surface = SurfaceSampler(_load(mi, area_probe()).scene)
    n = 1 << 20
    points = surface.sample(make_sampler(7, n), n)
    inv_pdf = np.array(1.0 / surface.density(points))
    y = np.array(points.si.p.y)
    cos = np.array(mi.Frame3f.cos_theta(points.si.wi))
    sphere_area = 4 * math.pi * 0.25 ** 2
    exact_height = 2 * math.pi * (-1.0 * 4.0 + 0.5 * sphere_area)
    exact_cosine = math.pi * (4.0 + sphere_area)
    assert np.mean(y * inv_pdf) == pytest.approx(exact_height, rel=0.01)
    assert np.mean(cos * inv_pdf) == pytest.approx(exact_cosine, rel=0.01)
    assert dr.all(points.weight == 1.0)  # both are one-sided diffuse: hemisphere sampling


def test_mis_incident_integral_under_a_constant_sky(mi):
    """Under a constant sky of radiance 1, a diffuse plane reflects exactly its albedo ρ, and
    ∂L_r/∂ρ_c = 1 in channel c. The MIS estimate (emitter + BSDF sampling) of Eq. 9 and its
    forward-mode derivative must reproduce both."""
    from services.solver.estimators.problem import Problem
    from services.solver.scene.params import ParameterSet
    from services.solver.training.residuals import differential_rhs, draw_batch, radiance_rhs
    from tests.support.scenes import sky_plane

    albedo = np.array([0.2, 0.5, 0.8])
    scene = _load(mi, sky_plane(albedo))
    problem = Problem(scene, ParameterSet(scene.params, ["plane-bsdf.reflectance.value"]))
    batch = draw_batch(problem, 4096, 64, seed=3, derivatives=True)
    assert batch.hit_index.numel() == 0            # nothing to hit but the sky
    l_r = radiance_rhs(batch, None).mean(0).numpy()
    assert l_r == pytest.approx(albedo, rel=0.015)
    d_l = differential_rhs(batch, None, None, problem.layout).mean(0).numpy()   # (P, 3)
    assert d_l == pytest.approx(np.eye(3), abs=0.015)

"""``direct`` and ``radiance-cache`` carry a texture (issue 24): ``dz/dp`` by one adjoint pass through
their own one-bounce estimate at the camera hits, never P images.

The gradient check: a 4 x 4 RGB albedo (48 scalars) on the back wall of the textured box, one
8 x 8 view, 4 spp. The adjoint ``dz/dp`` of ``z = Σ w · y`` (``w`` a fixed random weight image,
signs mixed) against the contraction ``Σ w · dI/dp_i`` of the forward-mode derivative images of a
few texels, formed by the same method with the same seed: the same camera rays and incident
samples, so the two are the same sum computed in two AD modes, not two estimates. Tolerance:
``rtol = 1e-4`` and ``atol = 1e-5`` of the largest compared entry: both are float32 Dr.Jit
evaluations of one estimate, summed in different orders (the adjoint reduces ``K = 256`` weighted
lanes in float32, the contraction in float64); measured agreement about 1e-7 relative. For
``radiance-cache`` the cache ``L_phi`` is an untrained field (its values are arbitrary but fixed,
which is all the check needs: the term ``∂T · L_phi(x')`` is then non-zero and differs from
``direct``'s).
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from schemas.errors import InvalidJob
from schemas.job import JobSpec

KEY = "wall.reflectance.data"
TEXELS = [0 * 3 + 0, 5 * 3 + 1, 10 * 3 + 2]   # (row, col, channel): (0,0,R) (1,1,G) (2,2,B); 3: one forward graph


def _problem():
    from services.solver.estimators.problem import Problem
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.scene.textured import textured_box

    scene = load_scene(mitsuba_dict=textured_box(size=4, views=1, film=8))
    params = ParameterSet(scene.params, [KEY])
    params.assign(np.full(params.n, 0.5))
    return Problem(scene, params)


def test_adjoint_dz_dp_equals_the_forward_mode_contraction(mi):
    from schemas.solver import FieldConfig
    from services.solver.estimators.layout import DerivativeLayout
    from services.solver.estimators.methods import Fields, contract
    from services.solver.estimators.methods.camera_hit import Direct, RadianceCache
    from services.solver.fields.field import NeuralField

    problem = _problem()
    lo, hi = problem.bbox
    torch.manual_seed(0)
    w = np.random.default_rng(0).uniform(-1.0, 1.0, (8, 8, 3)).astype(np.float32)
    gradients = {}
    for method, fields in ((Direct(), Fields()), (RadianceCache(), Fields(NeuralField(FieldConfig(), 3, lo, hi)))):
        problem.layout = DerivativeLayout.by_component([problem.parameters.n])
        adjoint = method.loss_gradient(problem, fields, w, spp=4, seed=3)
        assert adjoint.shape == (48,) and np.count_nonzero(adjoint) == 48      # every texel of the seen wall
        problem.layout = DerivativeLayout(tuple(TEXELS), ((0, 1, 2),) * len(TEXELS))   # images of these texels only
        explicit = contract(method.gradient_images(problem, fields, spp=4, seed=3), w)[TEXELS]
        scale = np.abs(explicit).max()
        assert np.min(np.abs(explicit)) > 0.05 * scale, explicit               # a real check: every texel counts
        np.testing.assert_allclose(adjoint[TEXELS], explicit, rtol=1e-4, atol=1e-5 * scale)
        gradients[method.name] = adjoint
    assert np.linalg.norm(gradients["direct"] - gradients["radiance-cache"]) > 0.01 * np.linalg.norm(gradients["direct"])


def test_the_probe_plans_a_texture_as_one_unit(mi):
    """The effect probe of ``radiance-cache`` differentiates a texture along the sum of its texels
    (one traversal, not one per texel): its plan has one active entry for the 48 texels, and the
    layout carries every texel."""
    from services.solver.scene.effects import choose_effects
    from services.solver.scene.facts import probe_scene

    problem = _problem()
    facts = probe_scene(problem.scene, problem.parameters, probe_rays=1 << 10, probe_depth=2)
    assert [(s.label, s.size) for s in facts.scalars] == [(KEY, 48)] and facts.scalars[0].first_bounce == 0
    plan = choose_effects(facts, "radiance-cache", {"radiance"})
    assert plan.bsdf_term.value and len(plan.scalars) == 1 and plan.scalars[0].active
    problem.simulate(plan)
    assert problem.layout.scalars == tuple(range(48))


def _job(**changes) -> JobSpec:
    job = {"scene": {"builtin": "textured-box"}, "parameters": [{"key": KEY, "init": 0.5}],
           "targets": {"synthetic": {"values": {KEY: None}, "spp": 4}}, "iterations": 2, "method": "direct",
           "render": {"resolution": [8, 8]}}
    job.update(changes)
    return JobSpec.model_validate(job)


def test_a_direct_texture_job_runs(mi, tmp_path):
    import json

    from services.jobs.local import run_local

    summary = run_local(_job(), tmp_path / "job")
    assert summary["status"] == "succeeded", summary
    assert summary["method"] == "direct"
    record = json.loads((tmp_path / "job" / "iterations" / "000001" / "record.json").read_text())
    assert record["textures"][KEY]["gradient_rms"] > 0.0
    final = np.load(tmp_path / "job" / summary["textures"][KEY]["npy"])
    assert final.shape == (64, 64, 3) and not np.allclose(final, 0.5)        # Adam moved the texels


@pytest.mark.parametrize("method", ["direct", "radiance-cache"])
def test_direct_and_radiance_cache_accept_a_texture_but_not_a_second_order_optimizer(mi, method):
    from services.solver.optimize.setup import check

    check(_job(method=method))   # accepted: no InvalidJob
    for optimizer in ("gauss-newton", "levenberg-marquardt"):
        with pytest.raises(InvalidJob, match="P x P curvature") as refused:
            check(_job(method=method, optimizer=optimizer))
        assert refused.value.field == "optimizer"


def _poison_one_lane(lane: int):
    """A Dr.Jit op that returns its ``mi.Color3f`` input unchanged but multiplies the derivative of
    lane ``lane`` by ``inf``, in both AD modes: a ray whose value is finite and whose derivative
    is not."""
    import drjit as dr
    import mitsuba as mi

    class Poison(dr.CustomOp):
        def eval(self, x):
            self.factor = dr.select(dr.arange(mi.UInt32, dr.width(x)) == lane, dr.inf, 1.0)
            return mi.Color3f(x)

        def forward(self):
            self.set_grad_out(self.grad_in("x") * self.factor)

        def backward(self):
            self.set_grad_in("x", self.grad_out() * self.factor)

        def name(self):
            return "poison"

    return lambda x: dr.custom(Poison, x)


@pytest.mark.parametrize("method", ["direct", "radiance-cache"])
def test_a_ray_with_a_non_finite_derivative_is_dropped_and_counted(mi, monkeypatch, method):
    """One camera ray (pixel (4, 4) at 1 spp: lane 36 in pixel-major order) whose incident
    ``emitted`` is finite but whose derivative is infinite: the adjoint ``dz/dp`` stays finite,
    equals the clean one with that pixel's ``dz/dy`` zeroed (the same sum without that ray; float32
    sums in another order: measured 1e-9 of the largest entry), and the guard counts that one ray
    under ``camera``, as the forward-mode path's guard does."""
    import drjit as dr

    from schemas.solver import FieldConfig
    from services.solver.estimators.layout import DerivativeLayout
    from services.solver.estimators.methods import Fields, camera_hit, make_method
    from services.solver.fields.field import NeuralField

    problem = _problem()
    problem.layout = DerivativeLayout.by_component([problem.parameters.n])
    lo, hi = problem.bbox
    torch.manual_seed(0)
    fields = Fields() if method == "direct" else Fields(NeuralField(FieldConfig(), 3, lo, hi))
    estimator = make_method(method)
    w = np.random.default_rng(0).uniform(-1.0, 1.0, (8, 8, 3)).astype(np.float32)
    without = w.copy()
    without[4, 4] = 0.0
    clean = estimator.loss_gradient(problem, fields, w, spp=1, seed=3)
    expected = estimator.loss_gradient(problem, fields, without, spp=1, seed=3)
    scale = np.abs(expected).max()
    assert np.abs(clean - expected).max() > 0.1 * scale       # the ray reads the texture: dropping it shows
    assert problem.sanitized == {}

    poison, attached = _poison_one_lane(4 * 8 + 4), camera_hit.evaluate_attached

    def poisoned(*args, **kwargs):
        emitted, throughput = attached(*args, **kwargs)
        with dr.resume_grad():
            return poison(emitted), throughput

    monkeypatch.setattr(camera_hit, "evaluate_attached", poisoned)
    gradient = estimator.loss_gradient(problem, fields, w, spp=1, seed=3)
    assert np.all(np.isfinite(gradient)), np.count_nonzero(~np.isfinite(gradient))
    np.testing.assert_allclose(gradient, expected, rtol=1e-5, atol=1e-6 * scale)
    assert problem.sanitized == {"camera": 1}


def test_a_radiance_cache_texture_job_runs(mi, tmp_path):
    """``radiance-cache`` with a texture, end to end through ``run_local``: the planner trains
    ``L_phi`` (the textured box's light bounces), each iteration trains it a few steps and takes
    ``dz/dp`` by the adjoint pass through the one-bounce estimate with ``L_phi`` at ``x'``; Adam
    moves the texels and every record stays finite. Kept cheap: 8 x 8 films, 2 iterations, a
    256-point residual batch, 10 warm-up steps."""
    import json

    from services.jobs.local import run_local

    training = {"residual_points": 256, "incident_samples": 2, "warmup_steps": 10, "steps_per_iteration": 2}
    summary = run_local(_job(method="radiance-cache", training=training), tmp_path / "job")
    assert summary["status"] == "succeeded", summary
    assert summary["method"] == "radiance-cache" and summary["iterations"] == 2
    plan = json.loads((tmp_path / "job" / "plan.json").read_text())
    assert plan["fields"]["radiance"] and not plan["fields"]["differential"]
    for k in range(2):
        record = json.loads((tmp_path / "job" / "iterations" / f"{k:06d}" / "record.json").read_text())
        assert record["residual_radiance"] is not None and np.isfinite(record["residual_radiance"])
        texture = record["textures"][KEY]
        assert np.isfinite(texture["gradient_rms"]) and texture["gradient_rms"] > 0.0
        assert "camera" not in record["sanitized"], record["sanitized"]
    final = np.load(tmp_path / "job" / summary["textures"][KEY]["npy"])
    assert final.shape == (64, 64, 3) and np.all(np.isfinite(final)) and not np.allclose(final, 0.5)

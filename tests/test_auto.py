"""``"method": "auto"``: the cost model (pure), the pick recorded in the plan and the checkpoint,
and an auto job computing exactly what a job naming its pick computes."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.test_loop import _run, small_job


def _cost(method="ndrf-lhs", fresh=0.4, evaluate=0.2, reuse=0.1, gradient=0.5, images=0.3):
    from services.solver.optimize.auto import MeasuredCost

    return MeasuredCost(method, fresh, evaluate, reuse, gradient, images)


def test_the_cost_model_adds_up_the_measured_parts():
    from services.solver.optimize.auto import Pool, predict

    # pool of 8 batches each used 4 times; 20 warm-up steps, 10 per iteration, 2 sensors, images every other iteration
    p = predict(_cost(), iterations=5, sensors=2, warmup_steps=20, steps_per_iteration=10, images_fraction=0.5,
                pool=Pool(chunks=8, reuse=4))
    warmup = 20 * (0.25 * 0.4 + 0.75 * 0.1)                         # a quarter of the steps draw, the rest reuse
    tuning = 8 * (0.25 * 0.4 + 0.75 * 0.2) + 2 * 0.1                # 8 stale batches after a step, 2 up to date
    assert p.warmup_seconds == pytest.approx(warmup)
    assert p.iteration_seconds == pytest.approx(tuning + 2 * (0.5 + 0.5 * 0.3))
    assert p.total_seconds == pytest.approx(warmup + 5 * p.iteration_seconds)

    plain = predict(_cost(), iterations=5, sensors=1, warmup_steps=20, steps_per_iteration=10, images_fraction=1.0,
                    pool=None)                                      # without the pool every step draws
    assert plain.warmup_seconds == pytest.approx(20 * 0.4)
    assert plain.iteration_seconds == pytest.approx(10 * 0.4 + 0.5 + 0.3)

    prb = predict(_cost("prb", 0, 0, 0, gradient=0.2, images=0.9), iterations=5, sensors=3, warmup_steps=400,
                  steps_per_iteration=20, images_fraction=0.0, pool=Pool(8, 4))
    assert prb.warmup_seconds == 0 and prb.iteration_seconds == pytest.approx(3 * 0.2)   # no field, no training
    with pytest.raises(ValueError, match=r"images_fraction must lie in \[0, 1\]"):
        predict(_cost(), iterations=1, sensors=1, warmup_steps=0, steps_per_iteration=0, images_fraction=2.0,
                pool=None)


def test_auto_picks_the_smallest_prediction_and_says_by_how_much():
    from services.solver.optimize.auto import Pool, choose, predict

    def at(iterations):
        common = dict(iterations=iterations, sensors=1, warmup_steps=100, steps_per_iteration=4, images_fraction=0.0,
                      pool=Pool(8, 4))
        return [predict(_cost("prb", 0, 0, 0, gradient=1.0), **common),
                predict(_cost("ndrf-lhs", 0.1, 0.1, 0.1, gradient=0.1), **common)]

    # the fields' warm-up (10 s) pays off only over enough iterations: 1.0 s against 0.5 s per iteration
    assert choose(at(10), 10)[0] == "prb"
    method, reason = choose(at(100), 100)
    assert method == "ndrf-lhs"
    assert "ndrf-lhs 60.0 s (warm-up 10.0 s + 0.500 s/iteration), 1.7x ahead" in reason and "prb 100.0 s" in reason
    with pytest.raises(ValueError, match="no candidate"):
        choose([], 10)


def test_a_tie_within_the_trials_noise_goes_to_the_preferred_method():
    from services.solver.optimize.auto import TIE, Pool, choose, predict

    def run(method, gradient):
        return predict(_cost(method, 0.1, 0.1, 0.1, gradient=gradient), iterations=10, sensors=1, warmup_steps=0,
                       steps_per_iteration=0, images_fraction=0.0, pool=Pool(8, 4))

    rhs, lhs = run("ndrf-rhs", 1.0), run("ndrf-lhs", 1.0 * (TIE - 0.01))
    method, reason = choose([rhs, lhs], 10)
    assert method == "ndrf-lhs" and "a tie" in reason and "ndrf-rhs 10.0 s" in reason
    assert choose([rhs, run("ndrf-lhs", TIE + 0.01)], 10)[0] == "ndrf-rhs"      # beyond the tie: the fastest


def test_gradient_images_count_every_iteration_only_for_gauss_newton():
    from schemas.job import JobSpec
    from services.solver.optimize.auto import images_fraction

    assert images_fraction(JobSpec.model_validate(small_job(iterations=10, images_every=1))) == 1.0
    assert images_fraction(JobSpec.model_validate(small_job(iterations=10, images_every=5))) == 0.3   # 0, 5 and 9
    assert images_fraction(JobSpec.model_validate(small_job(iterations=10, images_every=100))) == 0.2  # first, last
    assert images_fraction(JobSpec.model_validate(small_job(iterations=10, images_every=100,
                                                            optimizer="gauss-newton"))) == 1.0


def test_the_job_schema_takes_auto_and_nothing_else_new():
    from pydantic import ValidationError

    from schemas.job import JobSpec

    assert JobSpec.model_validate(small_job("auto")).method == "auto"
    with pytest.raises(ValidationError, match="'ndrf-lhs', 'ndrf-rhs', 'radiance-cache', 'direct' or 'prb'"):
        JobSpec.model_validate(small_job("fastest"))


def test_an_auto_job_runs_its_pick_exactly_and_says_why(mi, tmp_path):
    """The trial must leave no trace in the run it chooses: same samples, same fields, same
    parameters as a job that names the picked method (torch's random state is restored, the
    chosen method's fields are built fresh)."""
    from schemas.methods import AUTO_CANDIDATES

    auto = _run(small_job("auto", iterations=3), tmp_path / "auto")
    assert auto["status"] == "succeeded"
    plan = json.loads((tmp_path / "auto" / "plan.json").read_text())
    picked = plan["auto"]["picked"]
    assert plan["method"] == picked and picked in AUTO_CANDIDATES
    predictions = plan["auto"]["predictions"]
    assert sorted(p["method"] for p in predictions) == sorted(AUTO_CANDIDATES)
    assert predictions[0]["method"] == picked                       # sorted, fastest first
    assert all(p["total_seconds"] > 0 for p in predictions) and picked in plan["auto"]["reason"]
    record = json.loads((tmp_path / "auto" / "record.json").read_text())
    assert record["method"] == "auto"                                 # what was asked; the plan says what ran

    named = _run(small_job(picked, iterations=3), tmp_path / "named")
    assert np.allclose(auto["final"], named["final"], rtol=1e-7, atol=0)


def test_a_resumed_auto_job_keeps_the_pick_of_its_checkpoint(mi, monkeypatch):
    """Timings differ between attempts; the method must not: the pick comes from the checkpoint,
    and no trial runs."""
    from schemas.job import JobSpec
    from services.solver.optimize import checkpoint, loop

    spec = JobSpec.model_validate(small_job("auto"))
    blob = checkpoint.dumps(spec=spec, next_iteration=2, parameters=np.zeros(3), adam={}, trainer=None,
                            method="ndrf-rhs")
    assert checkpoint.method_of(blob) == "ndrf-rhs"

    def no_trial(prepared, between):
        raise AssertionError("a resumed auto job ran the trial again")

    monkeypatch.setattr(loop, "choose_method", no_trial)
    run = loop.InverseRenderingRun(spec, reporter=None, resume=blob)
    name, choice = run._method_name(prepared=None)
    assert name == "ndrf-rhs" and "earlier attempt" in choice["reason"]


def test_an_auto_job_can_be_canceled_during_its_trial(mi, tmp_path):
    """The cancel check runs between the trial's measurements: canceled before any plan exists."""
    summary = _run(small_job("auto"), tmp_path / "job", should_stop=lambda: "canceled")
    assert summary["status"] == "canceled" and summary["iterations"] == 0
    events = [json.loads(line)["type"] for line in (tmp_path / "job" / "events.jsonl").read_text().splitlines()]
    assert "auto" in events and "plan" not in events

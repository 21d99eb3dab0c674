"""The recipe of a run (``services/solver/optimize/recipe.py``): what ``auto`` chooses before the
first iteration and why, what a job's own choices leave alone, and how the batch grows."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from schemas.job import JobSpec
from services.solver.estimators.layout import DerivativeLayout
from services.solver.optimize.recipe import INDIRECT_SPP, MAX_GROWTH, MAX_JACOBIAN_RENDERS, choose_recipe, grow_batch
from services.solver.scene.planner import ScalarPlan


def _spec(**extra) -> JobSpec:
    job = {"scene": {"builtin": "room-open-8"},
           "parameters": [{"key": "walls.reflectance.value"}, {"key": "ball.reflectance.value"}],
           "targets": {"synthetic": {"values": {"walls.reflectance.value": 0.8, "ball.reflectance.value": 0.3}}}}
    return JobSpec.model_validate({**job, **extra})


def _problem(sizes, first_bounces=None):
    plan = None if first_bounces is None else SimpleNamespace(scalars=[
        ScalarPlan(f"s{i}", bounce is not None, (0, 1, 2), "", bounce) for i, bounce in enumerate(first_bounces)])
    return SimpleNamespace(layout=DerivativeLayout.by_component(sizes), plan=plan,
                           parameters=SimpleNamespace(has_textures=False, n=sum(sizes)))


def test_the_default_job_gets_prb_levenberg_marquardt_and_one_view_with_reasons():
    recipe = choose_recipe(_spec(), _problem([3, 3]), sensors=8)
    assert (recipe.method, recipe.optimizer, recipe.jacobian, recipe.views, recipe.spp) == (
        "prb", "levenberg-marquardt", "method", 1, 1)
    assert recipe.adaptive_views and recipe.depth.unbiased
    said = {d.what: d for d in recipe.decisions}
    assert set(said) == {"method", "optimizer", "views", "spp", "depth", "trust_growth", "trust_start"}
    assert recipe.trust_growth == 1.5 and "not measured" in said["trust_growth"].reason
    assert recipe.trust_start == 1.0 and "not measured" in said["trust_start"].reason
    assert "2 forward render(s) per view" in said["optimizer"].reason           # 6 scalars, 2 channel groups
    assert all(d.iteration is None and d.reason for d in recipe.decisions)     # decided before iteration 0
    assert recipe.to_json()["decisions"][0]["what"] == "method"


def test_auto_takes_adam_when_the_jacobian_is_dear_or_there_is_no_model():
    many = choose_recipe(_spec(), _problem([1] * (MAX_JACOBIAN_RENDERS + 1)), sensors=8)
    assert many.optimizer == "adam" and "forward renders per view" in many.decisions[-3].reason
    assert not many.adaptive_views                                              # Adam averages the noise itself
    l1 = choose_recipe(_spec(loss="l1"), _problem([3, 3]), sensors=8)
    assert l1.optimizer == "adam" and any("l1 loss" in d.reason for d in l1.decisions)


def test_the_jobs_own_choices_are_kept_and_not_explained_as_auto():
    recipe = choose_recipe(_spec(method="ndrf-lhs", optimizer="adam", views_per_iteration=2), _problem([3, 3]),
                           sensors=8)
    assert (recipe.method, recipe.optimizer, recipe.views, recipe.adaptive_views) == ("ndrf-lhs", "adam", 2, False)
    assert {d.what for d in recipe.decisions} <= {"depth", "spp"}
    assert choose_recipe(_spec(views_per_iteration=20), _problem([3, 3]), sensors=8).views == 8


def test_the_batch_grows_views_first_then_samples_and_stops():
    recipe = choose_recipe(_spec(), _problem([3, 3]), sensors=4)
    grown = [grow_batch(recipe, 4, k) for k in range(10)]
    sizes = [(d.what, d.value) for d in grown if d is not None]
    assert sizes == [("views", 2), ("views", 4), ("spp", 2), ("spp", 4)]      # 4 views x 4 spp = 16 x the first
    assert recipe.views * recipe.gradient_spp == MAX_GROWTH
    assert all(d.iteration is not None for d in recipe.decisions if d.what in ("views", "spp") and d.value != 1)
    fixed = choose_recipe(_spec(optimizer="adam"), _problem([3, 3]), sensors=4)
    assert grow_batch(fixed, 4, 0) is None


def test_a_truncated_depth_is_said_and_no_roulette_needs_a_depth():
    from pydantic import ValidationError

    recipe = choose_recipe(_spec(render={"max_depth": 12}), _problem([3, 3]), sensors=8)
    assert not recipe.depth.unbiased and "biased" in recipe.depth.describe()
    with pytest.raises(ValidationError, match="needs a finite render.max_depth"):
        _spec(render={"rr_depth": None})


def test_the_trust_region_grows_faster_where_light_leaves_the_scene():
    from services.solver.optimize.recipe import CLOSED, CLOSED_GROWTH, CLOSED_START, OPEN_GROWTH, OPEN_START

    asked = []

    def measured(value):
        return lambda: asked.append(value) or value

    opened = choose_recipe(_spec(), _problem([3, 3]), sensors=8, closure=measured(0.85))
    closed = choose_recipe(_spec(), _problem([3, 3]), sensors=8, closure=measured(CLOSED))
    assert (opened.trust_growth, closed.trust_growth) == (OPEN_GROWTH, CLOSED_GROWTH)
    assert (opened.trust_start, closed.trust_start) == (OPEN_START, CLOSED_START) and OPEN_START > CLOSED_START
    said = [{d.what: d for d in r.decisions} for r in (opened, closed)]
    assert "85% of the light" in said[0]["trust_growth"].reason and "closed scene" in said[1]["trust_growth"].reason
    assert opened.to_json()["trust_growth"] == OPEN_GROWTH and opened.to_json()["trust_start"] == OPEN_START
    adam = choose_recipe(_spec(optimizer="adam"), _problem([3, 3]), sensors=8, closure=measured(0.1))
    assert asked == [0.85, CLOSED] and adam.trust_growth == CLOSED_GROWTH   # measured only for Levenberg-Marquardt


def test_scalars_seen_only_through_interreflection_start_at_more_samples():
    hidden = choose_recipe(_spec(), _problem([3], first_bounces=[1, 2, 1]), sensors=1)
    assert (hidden.spp, hidden.gradient_spp, hidden.first_size) == (INDIRECT_SPP, INDIRECT_SPP, INDIRECT_SPP)
    assert "seen directly" in {d.what: d for d in hidden.decisions}["spp"].reason
    grown = [grow_batch(hidden, 1, k) for k in range(6)]
    assert [d.value for d in grown if d is not None] == [2 * INDIRECT_SPP, 4 * INDIRECT_SPP, 8 * INDIRECT_SPP,
                                                        16 * INDIRECT_SPP]  # the growth is relative to the first
    seen = choose_recipe(_spec(), _problem([3], first_bounces=[0, 1, None]), sensors=1)   # one seen directly
    assert seen.spp == 1
    unset = choose_recipe(_spec(), _problem([3]), sensors=1)                              # nothing measured
    assert unset.spp == 1
    measured = choose_recipe(_spec(), _problem([3]), sensors=1, direct=lambda: [False] * 3)   # prb: no plan
    assert measured.spp == INDIRECT_SPP
    assert choose_recipe(_spec(), _problem([3]), sensors=1, direct=lambda: [False, True, False]).spp == 1
    own = choose_recipe(_spec(render={"spp": 2}), _problem([3], first_bounces=[1, 1, 1]), sensors=1)
    assert own.spp == 2                                                                   # the job's own choice
    other = choose_recipe(_spec(method="ndrf-lhs"), _problem([3], first_bounces=[1, 1, 1]), sensors=1)
    assert other.spp == 1                                                                 # measured for prb only

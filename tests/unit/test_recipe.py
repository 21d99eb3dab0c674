"""A job resolved into its recipe (``services/solver/optimize/resolve.py`` and its rules): what ``auto``
chooses before the first iteration and why, what a job's own choices leave alone, that the
recipe is frozen, and how the run's batch grows."""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import pytest

from schemas.job import JobSpec
from services.solver.optimize.recipe import BatchNow, Recipe
from services.solver.optimize.resolve import (
    CLOSED,
    CLOSED_GROWTH,
    CLOSED_START,
    INDIRECT_SPP,
    MAX_GROWTH,
    MAX_JACOBIAN_RENDERS,
    NDRF_MIN_WORK,
    OPEN_GROWTH,
    OPEN_START,
    resolve,
)
from services.solver.scene.effects import EffectChoice as Switch
from services.solver.scene.effects import Effects, ScalarEffect


def _spec(**extra) -> JobSpec:
    job = {"scene": {"builtin": "room-open-8"},
           "parameters": [{"key": "walls.reflectance.value"}, {"key": "ball.reflectance.value"}],
           "targets": {"synthetic": {"values": {"walls.reflectance.value": 0.8, "ball.reflectance.value": 0.3}}}}
    return JobSpec.model_validate({**job, **extra})


class Measures:
    """The measurements resolve may take, faked; ``asked`` lists what it asked for, in order."""

    def __init__(self, closure=None, direct=None, first_bounces=None):
        self._closure, self._direct, self._bounces = closure, direct, first_bounces
        self.asked: list[str] = []

    def facts(self):
        self.asked.append("facts")
        return self._bounces

    def closure(self):
        self.asked.append("closure")
        return self._closure

    def direct(self):
        self.asked.append("direct")
        return self._direct if self._direct is not None else [True] * 64

    def film(self):
        self.asked.append("film")
        return (128, 128)

    def missing_energy(self, depth):
        self.asked.append("missing_energy")
        return 0.25


@pytest.fixture
def effects_from_bounces(monkeypatch):
    """choose_effects faked: every scalar active in all channels, first reached after the bounces
    the Measures' ``first_bounces`` give (None: unreached)."""
    import services.solver.optimize.rules.fields as module

    def plan(bounces, *args, **kwargs):
        on = Switch(True, "")
        return Effects(on, on, on, on, Switch(0, ""), [
            ScalarEffect(f"s{i}", b is not None, (0, 1, 2), "", b) for i, b in enumerate(bounces)])

    monkeypatch.setattr(module, "choose_effects", plan)


def choose(spec: JobSpec, sizes, sensors: int, measures: Measures | None = None) -> Recipe:
    parameters = SimpleNamespace(has_textures=False, has_geometry=False, n=sum(sizes), sizes=list(sizes))
    return resolve(spec, parameters, sensors, measures or Measures())


def test_the_default_job_gets_prb_levenberg_marquardt_and_one_view_with_reasons():
    recipe = choose(_spec(), [3, 3], sensors=8)
    assert (recipe.method, recipe.steps.optimizer, recipe.jacobian, recipe.batch.views, recipe.batch.spp) == (
        "prb", "levenberg-marquardt", "method", 1, 1)
    assert recipe.batch.grows and recipe.depth.unbiased and recipe.effects is None and recipe.fields_for is None
    said = {d.what: d for d in recipe.decisions}
    assert set(said) == {"method", "optimizer", "views", "spp", "depth", "trust_growth", "trust_start", "stop"}
    assert recipe.stop.auto and recipe.stop.standard_error is None
    assert recipe.steps.trust_growth == 1.5 and "no reflecting surface" in said["trust_growth"].reason
    assert recipe.steps.trust_start == 1.0
    assert "2 forward render(s) per view" in said["optimizer"].reason           # 6 scalars, 2 channel groups
    assert all(d.iteration is None and d.reason for d in recipe.decisions)     # decided before iteration 0
    assert recipe.to_json()["decisions"][0]["what"] == "method"


def test_the_recipe_is_frozen():
    recipe = choose(_spec(), [3, 3], sensors=8)
    with pytest.raises(dataclasses.FrozenInstanceError):
        recipe.method = "ndrf-lhs"  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        recipe.batch.views = 4  # type: ignore[misc]
    assert isinstance(recipe.decisions, tuple)


def test_auto_takes_adam_when_the_jacobian_is_dear_or_there_is_no_model():
    many = choose(_spec(), [1] * (MAX_JACOBIAN_RENDERS + 1), sensors=8)
    assert many.steps.optimizer == "adam" and "forward renders per view" in {
        d.what: d for d in many.decisions}["optimizer"].reason
    assert not many.batch.grows                                                 # Adam averages the noise itself
    l1 = choose(_spec(loss="l1"), [3, 3], sensors=8)
    assert l1.steps.optimizer == "adam" and any("l1 loss" in d.reason for d in l1.decisions)


def test_the_jobs_own_choices_are_kept_and_not_explained_as_auto(effects_from_bounces):
    recipe = choose(_spec(method="ndrf-lhs", optimizer="adam", views_per_iteration=2), [3, 3], sensors=8,
                    measures=Measures(first_bounces=[0] * 6))
    assert (recipe.method, recipe.steps.optimizer, recipe.batch.views, recipe.batch.grows) == (
        "ndrf-lhs", "adam", 2, False)
    assert recipe.fields_for == "ndrf-lhs" and recipe.effects is not None
    assert {d.what for d in recipe.decisions} <= {"depth", "spp", "stop"}
    assert choose(_spec(views_per_iteration=20), [3, 3], sensors=8).batch.views == 8


def test_the_batch_grows_views_first_then_samples_and_stops():
    recipe = choose(_spec(), [3, 3], sensors=4)
    batch = BatchNow.first(recipe.batch)
    grown = [batch.grow(recipe.batch, 4, k) for k in range(10)]
    sizes = [(d.what, d.value) for d in grown if d is not None]
    assert sizes == [("views", 2), ("views", 4), ("spp", 2), ("spp", 4)]      # 4 views x 4 spp = 16 x the first
    assert batch.views * batch.gradient_spp == MAX_GROWTH
    assert all(d.iteration == k for k, d in enumerate(grown) if d is not None)
    assert recipe.batch.views == 1                                              # the recipe itself never changes
    fixed = choose(_spec(optimizer="adam"), [3, 3], sensors=4)
    assert BatchNow.first(fixed.batch).grow(fixed.batch, 4, 0) is None


def test_a_truncated_depth_is_said_with_what_it_misses_and_no_roulette_needs_a_depth():
    from pydantic import ValidationError

    measures = Measures()
    recipe = choose(_spec(render={"max_depth": 12}), [3, 3], sensors=8, measures=measures)
    assert not recipe.depth.unbiased and "biased" in recipe.depth.describe()
    assert "missing_energy" in measures.asked and "misses 25.0%" in recipe.warnings[0]
    unbiased = Measures()
    assert not choose(_spec(), [3, 3], sensors=8, measures=unbiased).warnings
    assert "missing_energy" not in unbiased.asked                               # measured only when truncated
    with pytest.raises(ValidationError, match="needs a finite render.max_depth"):
        _spec(render={"rr_depth": None})


def test_the_trust_region_grows_faster_where_light_leaves_the_scene():
    opened = choose(_spec(), [3, 3], sensors=8, measures=Measures(closure=0.85))
    closed = choose(_spec(iterations=10), [3, 3], sensors=8, measures=Measures(closure=CLOSED))  # a short run: prb
    assert (opened.steps.trust_growth, closed.steps.trust_growth) == (OPEN_GROWTH, CLOSED_GROWTH)
    assert (opened.steps.trust_start, closed.steps.trust_start) == (OPEN_START, CLOSED_START)
    assert OPEN_START > CLOSED_START
    said = [{d.what: d for d in r.decisions} for r in (opened, closed)]
    assert "85% of the light" in said[0]["trust_growth"].reason and "closed scene" in said[1]["trust_growth"].reason
    assert opened.to_json()["trust_growth"] == OPEN_GROWTH and opened.to_json()["trust_start"] == OPEN_START
    adam = Measures(closure=0.1)
    assert choose(_spec(optimizer="adam"), [3, 3], sensors=8, measures=adam).steps.trust_growth == CLOSED_GROWTH
    assert "closure" not in adam.asked                                          # measured only for Levenberg-Marquardt


def test_auto_trains_a_field_in_a_closed_scene_whose_run_pays_for_the_warm_up(effects_from_bounces):
    pixels = 128 * 128
    long_run = -(-NDRF_MIN_WORK // pixels)                      # the fewest iterations that pay (at 128x128)
    closed = Measures(closure=CLOSED, first_bounces=[1] * 6)
    recipe = choose(_spec(iterations=long_run), [3, 3], sensors=8, measures=closed)
    said = {d.what: d for d in recipe.decisions}
    assert recipe.method == "ndrf-lhs" and recipe.steps.optimizer == "levenberg-marquardt"
    assert "closed scene" in said["method"].reason and "pareto-ndrf" in said["method"].reason
    assert recipe.differential and recipe.fields_for == "ndrf-lhs"  # its dL_theta is trained for it
    short = choose(_spec(iterations=long_run - 1), [3, 3], sensors=8, measures=Measures(closure=CLOSED))
    assert short.method == "prb" and "warm-up would cost more" in {d.what: d for d in short.decisions}["method"].reason
    opened = choose(_spec(iterations=10 * long_run), [3, 3], sensors=8, measures=Measures(closure=CLOSED - 0.01))
    assert opened.method == "prb" and "open scene" in {d.what: d for d in opened.decisions}["method"].reason
    for other in ({"loss": "l1"}, {"optimizer": "adam"}, {"jacobian": "differential-field"}):
        asked = Measures(closure=1.0, first_bounces=[1] * 6)
        assert choose(_spec(iterations=long_run, **other), [3, 3], sensors=8, measures=asked).method == "prb", other
        assert "film" not in asked.asked                       # no field unless Levenberg-Marquardt steps on l2
    assert choose(_spec(iterations=long_run), [3] * 5, sensors=8, measures=closed).method == "prb"  # > 12 scalars


def test_auto_keeps_prb_for_a_hidden_scalar_in_a_closed_scene(effects_from_bounces):
    """A closed scene whose run pays for the warm-up, but one of its scalars is seen only through
    interreflection (bright-room's hidden sphere): prb, with the reason. At equal seconds prb's
    answer was better there (bench/results/pareto-bright.md)."""
    pixels = 128 * 128
    long_run = -(-NDRF_MIN_WORK // pixels)
    hidden = Measures(closure=CLOSED, first_bounces=[1] * 6, direct=[True] * 3 + [False] * 3)
    recipe = choose(_spec(iterations=long_run), [3, 3], sensors=1, measures=hidden)
    reason = {d.what: d for d in recipe.decisions}["method"].reason
    assert recipe.method == "prb" and "seen only through interreflection" in reason and "pareto-bright" in reason
    seen = Measures(closure=CLOSED, first_bounces=[1] * 6, direct=[True] * 6)
    assert choose(_spec(iterations=long_run), [3, 3], sensors=1, measures=seen).method == "ndrf-lhs"


def test_scalars_seen_only_through_interreflection_start_at_more_samples(effects_from_bounces):
    hidden = choose(_spec(), [3], sensors=1, measures=Measures(direct=[False] * 3))
    assert (hidden.batch.spp, hidden.batch.gradient_spp, hidden.batch.first_size) == (
        INDIRECT_SPP, INDIRECT_SPP, INDIRECT_SPP)
    assert "seen directly" in {d.what: d for d in hidden.decisions}["spp"].reason
    batch = BatchNow.first(hidden.batch)
    grown = [batch.grow(hidden.batch, 1, k) for k in range(6)]
    assert [d.value for d in grown if d is not None] == [2 * INDIRECT_SPP, 4 * INDIRECT_SPP, 8 * INDIRECT_SPP,
                                                        16 * INDIRECT_SPP]  # the growth is relative to the first
    assert choose(_spec(), [3], sensors=1, measures=Measures(direct=[True, False, False])).batch.spp == 1
    own = choose(_spec(render={"spp": 2}), [3], sensors=1, measures=Measures(direct=[False] * 3))
    assert own.batch.spp == 2                                                   # the job's own choice
    fields = choose(_spec(method="ndrf-lhs"), [3], sensors=1, measures=Measures(first_bounces=[1, 1, 1]))
    assert fields.batch.spp == 1                                                # the rule is prb's
    asked = Measures(first_bounces=[1, 2, 1])
    hybrid = choose(_spec(jacobian="differential-field"), [3], sensors=1, measures=asked)
    assert hybrid.batch.spp == INDIRECT_SPP and asked.asked[0] == "facts" and "direct" not in asked.asked
    assert hybrid.fields_for == "ndrf-lhs" and hybrid.method == "prb"          # the hybrid's effects say it

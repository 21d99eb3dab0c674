"""Experiments as pure logic: field paths, the grid x random x seeds product, validation of every
run before anything is queued, appends, and the metrics across runs (no scene is loaded here)."""

from __future__ import annotations

import csv
import io
import json
import math

import pytest

from harness.cluster import small_job
from schemas.errors import InvalidJob
from schemas.experiments import ExperimentSpec, RunRow
from schemas.records import IterationRecord, JobRecord, JobStatus
from services.experiments import results
from services.experiments.expand import (
    InvalidExperiment,
    check_sweep,
    count_runs,
    expand,
    get_path,
    job_document,
    merge,
    parse_path,
    set_path,
)
from services.experiments.service import normalize
from services.experiments.validate import check_run_count, validate_runs
from services.settings import Limits
from services.store.job import JobFiles
from services.store.local import FolderStore


def spec(**sweep) -> ExperimentSpec:
    return ExperimentSpec.model_validate({"base": small_job("direct", iterations=3), **sweep})


def test_field_paths_address_fields_list_entries_by_index_or_key_and_dict_keys():
    assert parse_path("training.steps_per_iteration") == ["training", "steps_per_iteration"]
    assert parse_path("parameters[0].init") == ["parameters", 0, "init"]
    assert parse_path("parameters[red.reflectance.value].init") == ["parameters", "red.reflectance.value", "init"]
    base, _ = normalize(spec())
    assert get_path(base, "parameters[red.reflectance.value].init") == [0.3, 0.3, 0.3]
    document = job_document(base, {"parameters[red.reflectance.value].init": 0.5,
                                    "targets.synthetic.values[red.reflectance.value]": [0.1, 0.2, 0.3],
                                    "render.resolution": [8, 8], "method": "prb"})
    assert document["parameters"][0]["init"] == 0.5 and document["method"] == "prb"
    assert document["targets"]["synthetic"]["values"]["red.reflectance.value"] == [0.1, 0.2, 0.3]
    assert base["parameters"][0]["init"] == [0.3, 0.3, 0.3]                 # the base is not changed
    for bad in ("", "a..b", "a.", "1abc", "a[0]x"):
        with pytest.raises(ValueError):
            parse_path(bad)
    with pytest.raises(KeyError, match="no field 'nope'"):
        set_path(base, "render.nope", 1)
    with pytest.raises(KeyError, match="no entry with key"):
        get_path(base, "parameters[green.reflectance.value].init")


def test_the_product_is_grid_times_samples_times_seeds_and_draws_are_seeded():
    s = spec(grid={"method": ["direct", "prb"], "render.spp": [2, 4, 8]},
             random={"learning_rate": {"min": 0.01, "max": 0.3, "log": True}}, samples=2, seeds=[1, 2])
    base, sweep = normalize(s)
    assert count_runs(sweep, base) == 24
    runs = expand(sweep, base)
    assert len(runs) == 24 == len({r.key for r in runs})
    assert [r.values["seed"] for r in runs[:4]] == [1, 2, 1, 2]                     # seeds innermost
    rates = sorted({r.values["learning_rate"] for r in runs})
    assert len(rates) == 2 and all(0.01 <= r <= 0.3 for r in rates)                  # 2 draws, shared by the grid
    assert check_sweep(sweep, base) == ["method", "render.spp", "learning_rate", "seed"]
    again = expand(sweep, base)
    assert [r.key for r in again] == [r.key for r in runs]                           # reproducible
    more = merge(sweep, {"samples": 1})
    extended = expand(more, base)
    assert {r.key for r in runs} < {r.key for r in extended} and len(extended) == 36  # earlier draws kept
    other = expand({**sweep, "random_seed": 7}, base)
    assert {r.values["learning_rate"] for r in other}.isdisjoint(rates)


def test_seeds_default_to_the_base_seed_and_grid_seed_is_read_as_seeds():
    base, sweep = normalize(spec(grid={"learning_rate": [0.1, 0.2]}))
    assert sweep["seeds"] == [1] and [r.values for r in expand(sweep, base)] == [
        {"learning_rate": 0.1, "seed": 1}, {"learning_rate": 0.2, "seed": 1}]
    _, sweep = normalize(spec(grid={"seed": [3, 4]}))
    assert sweep["seeds"] == [3, 4] and "seed" not in sweep["grid"]
    with pytest.raises(InvalidExperiment) as err:
        normalize(spec(grid={"seed": [3]}, seeds=[1]))
    assert err.value.field == "grid.seed"


def test_unknown_paths_and_inconsistent_sweeps_are_refused_naming_the_field():
    base, sweep = normalize(spec(grid={"training.nope": [1]}))
    with pytest.raises(InvalidExperiment) as err:
        check_sweep(sweep, base)
    assert err.value.field == "grid.training.nope" and "no field 'nope'" in err.value.message
    base, sweep = normalize(spec(samples=3))
    with pytest.raises(InvalidExperiment, match="samples > 1 needs"):
        check_sweep(sweep, base)
    with pytest.raises(ValueError):
        spec(random={"learning_rate": {"min": 0, "max": 1, "log": True}})          # the schema itself
    base, sweep = normalize(spec(random={"learning_rate": {"min": -1e308, "max": 1e308, "integer": True}}, samples=3))
    assert all(abs(r.values["learning_rate"]) <= 1e308 for r in expand(sweep, base))   # no overflow, no NaN


def test_every_run_is_validated_and_the_first_bad_one_is_named_with_its_field():
    calls = []

    def preflight(job, limits):
        calls.append(job)
        if job.render.spp == 8:
            raise InvalidJob("render.spp", "the scene says no")

    base, sweep = normalize(spec(grid={"learning_rate": [0.05, 0.1, -1.0]}, seeds=[1, 2]))
    with pytest.raises(InvalidExperiment) as err:
        validate_runs(base, expand(sweep, base), Limits(), preflight)
    assert err.value.field == "runs[4].learning_rate"
    assert "run 4 (learning_rate=-1.0, seed=1)" in err.value.message and "greater than 0" in err.value.message
    assert calls == []                                  # nothing reached the scene check

    base, sweep = normalize(spec(grid={"learning_rate": [0.05, 0.1], "render.spp": [4, 8]}, seeds=[1, 2]))
    with pytest.raises(InvalidExperiment) as err:
        validate_runs(base, expand(sweep, base), Limits(), preflight)
    assert err.value.field == "runs[2].render.spp"        # the first run with spp 8
    calls.clear()
    base, sweep = normalize(spec(grid={"learning_rate": [0.05, 0.1, 0.2]}, seeds=[1, 2, 3]))
    specs = validate_runs(base, expand(sweep, base), Limits(), preflight)
    assert len(specs) == 9 and len(calls) == 1           # one scene check for nine runs on one scene

    base, sweep = normalize(spec(grid={"render.spp": [4, 500]}))
    with pytest.raises(InvalidExperiment) as err:        # a cap, as for a single job
        validate_runs(base, expand(sweep, base), Limits(spp=256), None)
    assert err.value.field == "runs[1].render.spp" and "NDRF_MAX_SPP" in err.value.message


def test_the_run_cap_is_checked_before_expanding():
    base, sweep = normalize(spec(grid={"learning_rate": [0.01 * i for i in range(1, 101)]}, seeds=list(range(50))))
    with pytest.raises(InvalidExperiment) as err:
        check_run_count(sweep, base, Limits(experiment_runs=200))
    assert err.value.field == "grid" and "5000 runs exceed the limit of 200" in err.value.message


def test_append_adds_values_and_seeds_and_keeps_existing_runs():
    base, sweep = normalize(spec(grid={"method": ["direct", "prb"]}, seeds=[1, 2]))
    before = {r.key for r in expand(sweep, base)}
    more = merge(sweep, {"seeds": [3, 4, 1]})
    after = expand(more, base)
    assert len(after) == 8 and before < {r.key for r in after}
    assert len(expand(merge(sweep, {"grid": {"method": ["prb", "ndrf-lhs"]}}), base)) == 6
    with pytest.raises(InvalidExperiment) as err:
        merge(sweep, {"grid": {"learning_rate": [0.3]}})
    assert err.value.field == "grid.learning_rate"


# ------------------------------------------------------------------------------ metrics


def _job(store, job_id, status, losses, params, target, seconds=1.0):
    files = JobFiles(store, job_id)
    files.write(JobFiles.PLAN, {"init": [0.0], "target_values": target, "scalars": ["p"]})
    for k, (loss, p) in enumerate(zip(losses, params)):
        record = IterationRecord(iteration=k, loss=loss, parameters=[0.0], updated_parameters=[p], dz_dp=[0.0],
                                 learning_rate=0.1, seconds={"training": seconds / 2, "rendering": seconds / 2})
        store.put_json(files.iteration_key(k), record.model_dump(mode="json"))
    now = "2026-01-01T00:00:00.000+00:00"
    return JobRecord(id=job_id, status=status, method="prb", scene="cornell-box", created=now, updated=now,
                     started=now, finished="2026-01-01T00:00:10.000+00:00", iterations=len(losses))


def test_job_metrics_give_accuracy_against_compute_seconds(tmp_path):
    store = FolderStore(tmp_path)
    record = _job(store, "00000000000000000001", JobStatus.SUCCEEDED, [4.0, 2.0, 1.0], [0.5, 0.8, 0.95], [1.0], 2.0)
    metrics = results.job_metrics(JobFiles(store, record.id), record, target_error=0.25)
    assert metrics["seconds"] == [2.0, 4.0, 6.0] and metrics["loss"] == [4.0, 2.0, 1.0]
    assert metrics["parameter_error"] == pytest.approx([0.5, 0.2, 0.05])
    assert metrics["initial_error"] == 1.0 and metrics["time_to_error"] == 4.0     # first error <= 0.25
    assert metrics["final_parameter_error"] == pytest.approx(0.05) and metrics["wall_seconds"] == 10.0


def _row(index, status, seed, error, **varied):
    return RunRow(index=index, status=status, seed=seed, varied=varied, final_parameter_error=error,
                  final_loss=error and error * 10, seconds=float(index + 1), iterations=3)


def test_aggregates_best_run_and_csv():
    rows = [_row(0, "succeeded", 1, 0.1, method="prb"), _row(1, "succeeded", 2, 0.3, method="prb"),
            _row(2, "succeeded", 1, 0.05, method="direct"), _row(3, "failed", 2, None, method="direct")]
    groups = results.aggregates(None, rows)     # type: ignore[arg-type]
    assert [g.configuration for g in groups] == [{"method": "prb"}, {"method": "direct"}]
    prb = groups[0].metrics["final_parameter_error"]
    assert prb["mean"] == pytest.approx(0.2) and prb["std"] == pytest.approx(math.sqrt(0.02)) and prb["n"] == 2
    assert groups[1].succeeded == 1 and groups[1].metrics["final_parameter_error"]["std"] is None
    from schemas.experiments import Objective

    best = results.best_run(Objective(), rows)
    assert best.index == 2 and best.varied == {"method": "direct", "seed": 1} and best.value == 0.05
    assert results.best_run(Objective(metric="seconds", goal="max"), rows).index == 2
    table = list(csv.DictReader(io.StringIO(results.results_csv(rows))))
    assert [r["method"] for r in table] == ["prb", "prb", "direct", "direct"]
    assert float(table[1]["final_parameter_error"]) == 0.3 and table[3]["final_parameter_error"] == ""
    assert list(table[0])[:5] == ["run", "job", "status", "seed", "method"]


def test_curves_per_run_and_mean_over_seeds_per_configuration():
    from schemas.experiments import RunState

    def run(index, method, seed):
        return RunState(index=index, key=json.dumps([method, seed]), values={"method": method, "seed": seed})

    metric = lambda errors, seconds: {"iterations": len(errors), "seconds": seconds, "parameter_error": errors,
                                      "loss": [e * 2 for e in errors]}
    curves = results.curves([(run(0, "prb", 1), metric([0.4, 0.2, 0.1], [1, 2, 3])),
                             (run(1, "prb", 2), metric([0.6, 0.4], [2, 4])),
                             (run(2, "direct", 1), None)])
    assert [c.label for c in curves.runs] == ["#0", "#1"]
    (prb,) = curves.configurations
    assert prb.label == "method=prb" and prb.runs == [0, 1]
    assert prb.seconds == [1.5, 3.0] and prb.parameter_error == pytest.approx([0.5, 0.3])
    assert prb.parameter_error_spread == [[0.4, 0.6], [0.2, 0.4]]


def test_an_experiment_sweeps_the_requested_accuracy_and_each_run_stops_at_its_own():
    """Issue 37: "ask for an accuracy, and see the time it took" across an experiment's runs."""
    base, sweep = normalize(spec(grid={"stop.standard_error": [0.01, 0.002]}))
    assert check_sweep(sweep, base) == ["stop.standard_error"]
    jobs = validate_runs(base, expand(sweep, base), Limits(), None)
    assert [job.stop.standard_error for job in jobs] == [0.01, 0.002]
    with pytest.raises(InvalidExperiment, match="stop"):
        validate_runs(base, expand(normalize(spec(grid={"stop.standard_error": [-1.0]}))[1], base), Limits(), None)


def test_an_experiment_loads_at_most_experiment_checks_distinct_scenes_when_it_is_created():
    """Issue 38: 40 distinct render settings were 40 sandboxed checks in a row in the API."""
    calls = []
    base, sweep = normalize(spec(grid={"render.spp": list(range(1, 41))}))
    specs = validate_runs(base, expand(sweep, base), Limits(experiment_checks=4), lambda job, _: calls.append(job))
    assert len(specs) == 40 and [job.render.spp for job in calls] == [1, 2, 3, 4]

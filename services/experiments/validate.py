"""Every run of an experiment is a valid job, or nothing is queued.

Before an experiment (or an append) is stored, each planned run's job document is built and
checked as a job submission would be: the schema (pydantic), the caps (:func:`services.limits.
check_limits`), the target image headers, then the scene loaded in a sandboxed child
(``preflight``). The scene check is the expensive one; it only depends on the scene, the
parameters, the targets and the render settings, so it runs once per distinct combination of
those (a sweep over learning rates and seeds loads the scene once), and for at most
``NDRF_MAX_EXPERIMENT_CHECKS`` of them: the runs of the others are checked by the worker when they
run (a run whose scene does not load fails there, naming why), so one experiment cannot hold the
API's scene checks for minutes. The first failure is an
:class:`InvalidExperiment` naming the run and the field: ``runs[3].learning_rate``.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Callable, Sequence

from pydantic import ValidationError

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.validation import describe
from services.experiments.expand import InvalidExperiment, PlannedRun, count_runs, job_document
from services.limits import check_limits, check_target_headers
from services.settings import Limits

log = logging.getLogger(__name__)

#: ``preflight(spec, limits)``: raises InvalidJob naming a job field (services.jobs.preflight.preflight).
Preflight = Callable[[JobSpec, Limits], object]

#: Fields the sandboxed scene check reads; runs equal on these share one check.
SCENE_FIELDS = ("scene", "parameters", "targets", "render")


def check_run_count(sweep: dict, base: dict, limits: Limits, existing: int = 0) -> int:
    total = count_runs(sweep, base)
    if total > limits.experiment_runs:
        raise InvalidExperiment("grid", f"{total} runs exceed the limit of {limits.experiment_runs} runs per "
                                        f"experiment (NDRF_MAX_EXPERIMENT_RUNS): fewer values, samples or seeds")
    return total


def _describe_run(index: int, values: dict) -> str:
    shown = ", ".join(f"{k}={json.dumps(v)}" for k, v in values.items())
    return f"run {index} ({shown[:300]})"


def validate_runs(base: dict, runs: Sequence[PlannedRun], limits: Limits, preflight: Preflight | None,
                  first_index: int = 0) -> list[JobSpec]:
    """The job of every run, checked; raises :class:`InvalidExperiment` for the first bad run."""
    specs: list[JobSpec] = []
    for offset, run in enumerate(runs):
        index = first_index + offset
        try:
            spec = JobSpec.model_validate(job_document(base, run.values))
            check_limits(spec, limits)
        except ValidationError as exc:
            field, message = describe(exc)[0]
            raise InvalidExperiment(f"runs[{index}].{field}", f"{_describe_run(index, run.values)}: {message}") from None
        except InvalidJob as exc:
            raise InvalidExperiment(f"runs[{index}].{exc.field}",
                                    f"{_describe_run(index, run.values)}: {exc.message}") from None
        specs.append(spec)
    checked: set[str] = set()
    loaded = 0
    for offset, (run, spec) in enumerate(zip(runs, specs)):
        scene_key = json.dumps(spec.model_dump(mode="json", include=set(SCENE_FIELDS)), sort_keys=True)
        if scene_key in checked:
            continue
        checked.add(scene_key)
        index = first_index + offset
        try:
            check_target_headers(spec, limits)
            if preflight is not None and loaded < limits.experiment_checks:
                loaded += 1
                preflight(spec, limits)
        except InvalidJob as exc:
            raise InvalidExperiment(f"runs[{index}].{exc.field}",
                                    f"{_describe_run(index, run.values)}: {exc.message}") from None
    log.info("validated %d run(s): %d distinct scene setting(s), %d loaded in a sandbox now (the rest when "
             "they run, NDRF_MAX_EXPERIMENT_CHECKS)", len(specs), len(checked), loaded)
    return specs

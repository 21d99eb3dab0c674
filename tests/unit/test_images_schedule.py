"""When a run writes images (``services/solver/optimize/images.py``): off the iteration's path by
default (at most ``images_budget`` of the run's time), always at the last iteration and on request,
and every ``images_every`` iterations when the job says so."""

from __future__ import annotations

from schemas.job import JobSpec
from services.solver.optimize.images import ImageSchedule


def _spec(**extra) -> JobSpec:
    return JobSpec.model_validate({"scene": {"builtin": "cornell-box"}, "parameters": [{"key": "k"}],
                                   "targets": {"synthetic": {"values": {"k": 0.5}}}, "iterations": 200, **extra})


def _simulate(spec: JobSpec, iteration_seconds: float, image_seconds: float, asked=()) -> tuple[list[int], float]:
    schedule, written = ImageSchedule(), []
    for k in range(spec.iterations):
        due = schedule.due(k, spec, asked=k in asked, elapsed=iteration_seconds)
        schedule.spent(image_seconds if due else 0.0, iteration_seconds + (image_seconds if due else 0.0), written=due)
        if due:
            written.append(k)
    return written, schedule.image_seconds / schedule.run_seconds


def test_the_default_schedule_keeps_images_under_their_budget_and_writes_the_last():
    written, share = _simulate(_spec(), iteration_seconds=0.05, image_seconds=0.1)   # an image pass: 2 iterations
    assert share <= 0.05 + 1e-9 and written[-1] == 199 and len(written) >= 3
    assert 0 not in written                                     # never before the run has time to pay for it


def test_requests_and_a_fixed_interval_override_the_budget():
    written, _ = _simulate(_spec(), 0.05, 0.1, asked={3, 4})
    assert {3, 4} <= set(written)
    every, _ = _simulate(_spec(images_every=50), 0.05, 0.1)
    assert every == [0, 50, 100, 150, 199]

"""When a run ends before its cap of iterations (the job's ``stop``): at a requested accuracy, or
when more iterations would not improve its answer. Pure: it reads the answer
(:class:`~services.solver.optimize.answer.Estimate`) and how many iterations in a row ``auto``'s
condition has held (the loop counts them).

``standard_error``  every scalar's standard error at most ``T`` (or ``T x max(|estimate|, 0.01)``
                    with ``relative``): the accuracy the user asked for
``auto``            the run's own noise under half of the floor in every scalar
                    (``SE_run <= SE_floor / 2``: :mod:`.floor`): the total standard error is then
                    within 12% of the floor, and doubling the run would lower it by less than 6%;
                    and it has held at every iteration of the last :data:`HOLD_SHARE` of the run
                    (at least :data:`MIN_WINDOW` iterations): the floor is read from the run's
                    own candidates and moves by up to a third between iterations, and a rule
                    judged once stops on its high draws (on the demo, two seeds of five stopped
                    with twice the error the others reached at their cap)

Neither is judged before the answer averages :data:`SETTLED` iterations: a window of a few
iterations has a standard error too noisy to act on, nor before a shape job's last remesh (the
answer of a mesh about to be remeshed is not the run's).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from schemas.job import JobSpec
from services.solver.optimize.answer import MIN_WINDOW, Estimate

#: Iterations the answer must average before a rule may stop the run.
SETTLED = 2 * MIN_WINDOW
#: The smallest scale of a relative standard error (a scalar whose estimate is 0 is judged against this).
RELATIVE_FLOOR = 0.01
#: ``auto`` stops once the run's share of the error is at most this fraction of the floor's.
AUTO_SHARE = 0.5
#: ... and that has held over this share of the run's iterations so far (at least ``MIN_WINDOW``).
HOLD_SHARE = 0.25


@dataclass(frozen=True)
class StopRule:
    """The job's ``stop`` as the recipe resolved it: ``auto`` is off where there is no floor to
    compare with (a run without curvature)."""

    iterations: int
    standard_error: float | None
    relative: bool
    auto: bool
    not_before: int = 0    # the last remesh's iteration: the run goes on at least to its new stage

    def auto_holds(self, answer: Estimate) -> bool:
        """Whether ``auto``'s condition holds for this answer: the run's noise under
        :data:`AUTO_SHARE` of the floor in every scalar (judged from :data:`SETTLED` iterations on)."""
        run, floor = answer.run_error, answer.floor_error
        return (self.auto and answer.iterations >= SETTLED and answer.end >= self.not_before and run is not None
                and floor is not None and bool(np.all(run <= AUTO_SHARE * floor)))

    def reason(self, answer: Estimate, held: int = 0) -> str | None:
        """Why the run should stop now, or None to go on; ``held``: the iterations, this one
        included, at which :meth:`auto_holds` has held in a row."""
        if answer.standard_error is None or answer.iterations < SETTLED or answer.end < self.not_before:
            return None
        se = answer.standard_error
        if self.standard_error is not None:
            bound = self.standard_error * (np.maximum(np.abs(answer.values), RELATIVE_FLOOR) if self.relative else 1.0)
            if np.all(se <= bound):
                what = f"{self.standard_error:g} of its estimate" if self.relative else f"{self.standard_error:g}"
                return (f"the accuracy asked for: every scalar's standard error is at most {what} (largest "
                        f"{float(np.max(se)):.3g}, from iterations {answer.start} to {answer.end})")
        floor = answer.floor_error
        if floor is not None and self.auto_holds(answer) and held >= max(MIN_WINDOW, int(HOLD_SHARE * (answer.end + 1))):
            return (f"more iterations would not improve the answer: the run's own noise has been under half of what "
                    f"the targets' noise and the model's misfit leave in every scalar for {held} iterations (largest "
                    f"standard error {float(np.max(se)):.3g}, of which the floor {float(np.max(floor)):.3g})")
        return None


def stop_rule(spec: JobSpec, optimizer: str, decide: Callable[[str, str | int | float, str], None],
              not_before: int = 0) -> StopRule:
    """The job's ``stop`` as a rule for an ``optimizer``'s run (``auto`` needs a curvature), never
    stopping before ``not_before`` (a shape job's last remesh); ``decide(what, value, why)``
    records the choice in the plan."""
    asked = spec.stop
    auto = asked.auto and optimizer != "adam"
    if asked.auto and not auto:
        decide("stop", "iterations", f"the answer's floor needs the curvature of second-order steps, and {optimizer} "
                                     f"has none: the run ends at iterations ({spec.iterations})")
    elif auto:
        decide("stop", "auto", f"when more iterations would not improve the answer (the run's noise under half of "
                               f"the floor the targets' noise leaves, over the run's last quarter), at most "
                               f"{spec.iterations} iterations")
    return StopRule(spec.iterations, asked.standard_error, asked.relative, auto, not_before)

"""When a run ends before its cap of iterations (the job's ``stop``): at a requested accuracy, or
when more iterations would not improve its answer. Pure: it reads the answer only
(:class:`~services.solver.optimize.answer.Estimate`).

``standard_error``  every scalar's standard error at most ``T`` (or ``T x max(|estimate|, 0.01)``
                    with ``relative``): the accuracy the user asked for
``auto``            the run's own noise under half of the floor in every scalar
                    (``SE_run <= SE_floor / 2``: :mod:`.floor`): the total standard error is then
                    within 12% of the floor, and doubling the run would lower it by less than 6%

Neither is judged before the answer averages :data:`SETTLED` iterations: a window of a few
iterations has a standard error too noisy to act on, nor before a shape job's last remesh (the
answer of a mesh about to be remeshed is not the run's).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.solver.optimize.answer import MIN_WINDOW, Estimate

#: Iterations the answer must average before a rule may stop the run.
SETTLED = 2 * MIN_WINDOW
#: The smallest scale of a relative standard error (a scalar whose estimate is 0 is judged against this).
RELATIVE_FLOOR = 0.01
#: ``auto`` stops once the run's share of the error is at most this fraction of the floor's.
AUTO_SHARE = 0.5


@dataclass(frozen=True)
class StopRule:
    """The job's ``stop`` as the recipe resolved it: ``auto`` is off where there is no floor to
    compare with (a run without curvature)."""

    iterations: int
    standard_error: float | None
    relative: bool
    auto: bool
    not_before: int = 0    # the last remesh's iteration: the run goes on at least to its new stage

    def reason(self, answer: Estimate) -> str | None:
        """Why the run should stop now, or None to go on."""
        if answer.standard_error is None or answer.iterations < SETTLED or answer.end < self.not_before:
            return None
        se = answer.standard_error
        if self.standard_error is not None:
            bound = self.standard_error * (np.maximum(np.abs(answer.values), RELATIVE_FLOOR) if self.relative else 1.0)
            if np.all(se <= bound):
                what = f"{self.standard_error:g} of its estimate" if self.relative else f"{self.standard_error:g}"
                return (f"the accuracy asked for: every scalar's standard error is at most {what} (largest "
                        f"{float(np.max(se)):.3g}, from iterations {answer.start} to {answer.end})")
        run, floor = answer.run_error, answer.floor_error
        if self.auto and run is not None and floor is not None and np.all(run <= AUTO_SHARE * floor):
            return (f"more iterations would not improve the answer: the run's own noise is under half of what the "
                    f"targets' noise and the model's misfit leave in every scalar (largest standard error "
                    f"{float(np.max(se)):.3g}, of which the floor {float(np.max(floor)):.3g})")
        return None

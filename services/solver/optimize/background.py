"""Reports written beside the computation: :class:`BackgroundReporter` hands a run's reports to
one writer thread, so that an iteration's record, event and images are written while the next
iteration renders (Dr.Jit and torch release the GIL in their kernels).

The writer's Python work runs under the GIL, which the loop's thread needs back as soon as a
kernel returns: at CPython's default switch interval (5 ms, about a fifth of a 1-spp ``prb``
iteration on a CPU) a waiting loop thread would idle behind the writer. While the reporter is
open the interval is :data:`SWITCH_INTERVAL` (restored by :meth:`close`); ``python -m
bench.prb_iteration`` measures the loop with it.

Order is kept: reports reach the host's reporter in the order the loop made them, on one thread.
A checkpoint waits until it is written (a resume must find every record it keeps), and so does
:meth:`BackgroundReporter.flush`, which the loop calls before it declares success. What writing
raises (a fenced attempt, a full store) is raised again on the loop's thread at its next report,
checkpoint or flush, so the loop handles it as if the host had raised it there; reports made after
a failure are dropped, as the run is over.
"""

from __future__ import annotations

import logging
import queue
import sys
import threading

import numpy as np

from schemas.records import IterationRecord
from services.solver.optimize.report import RunReporter, StopReason

log = logging.getLogger(__name__)

#: Reports that may wait for the writer: beyond this the loop waits (a slow store slows the run
#: down rather than letting images pile up in memory).
DEPTH = 8

#: CPython's GIL switch interval (seconds) while a writer thread runs beside the loop.
SWITCH_INTERVAL = 0.0005

_CLOSE = object()


class BackgroundReporter:
    """A :class:`~services.solver.optimize.report.RunReporter` that forwards every report to
    ``host`` on a writer thread. ``should_stop`` and ``images_requested`` are asked of ``host``
    directly (they are polls, not reports). :meth:`close` ends the thread; use it once."""

    def __init__(self, host: RunReporter, depth: int = DEPTH):
        if depth < 1:
            raise ValueError(f"depth must be >= 1, got {depth}")
        self.host = host
        self._queue: queue.Queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._surfaced = False   # whether the loop's thread has seen _error
        self._switch_interval = sys.getswitchinterval()
        sys.setswitchinterval(min(self._switch_interval, SWITCH_INTERVAL))
        self._thread = threading.Thread(target=self._write, name="run-reports", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------ the writer

    def _write(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is _CLOSE:
                    return
                if self._error is None:
                    name, args = item
                    getattr(self.host, name)(*args)
            except BaseException as exc:  # handed to the loop's thread, never lost
                self._error = exc
            finally:
                self._queue.task_done()

    def _raise(self) -> None:
        if self._error is not None:
            self._surfaced = True
            raise self._error

    def _submit(self, name: str, *args) -> None:
        self._raise()
        self._queue.put((name, args))

    def flush(self) -> None:
        """Wait until every report so far is written; raise what writing raised."""
        self._queue.join()
        self._raise()

    def close(self) -> None:
        """Write what is queued, end the thread, and raise a failure the loop has not seen."""
        self._queue.put(_CLOSE)
        self._thread.join()
        sys.setswitchinterval(self._switch_interval)
        if self._error is not None and not self._surfaced:
            self._raise()

    # ------------------------------------------------------------- reports

    def plan(self, plan: dict) -> None:
        self._submit("plan", plan)

    def targets(self, images: dict[int, np.ndarray]) -> None:
        self._submit("targets", images)

    def progress(self, kind: str, payload: dict) -> None:
        self._submit("progress", kind, payload)

    def iteration(self, record: IterationRecord, renders: dict[int, np.ndarray] | None,
                  gradients: dict[int, np.ndarray] | None, silhouettes: dict[int, np.ndarray] | None = None) -> None:
        self._submit("iteration", record, renders, gradients, silhouettes)

    def textures(self, iteration: int | None, images: dict[str, np.ndarray]) -> None:
        self._submit("textures", iteration, images)

    def meshes(self, iteration: int, files: dict[str, bytes]) -> None:
        self._submit("meshes", iteration, files)

    def checkpoint(self, state: bytes, next_iteration: int) -> None:
        self._submit("checkpoint", state, next_iteration)
        self.flush()

    # --------------------------------------------------------------- polls

    def should_stop(self) -> StopReason | None:
        self._raise()
        return self.host.should_stop()

    def images_requested(self) -> bool:
        return self.host.images_requested()

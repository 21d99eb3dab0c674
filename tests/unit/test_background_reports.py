"""The writer thread of a run's reports (services/solver/optimize/background.py): order kept,
checkpoints written before the loop goes on, and a writer's failure raised on the loop's thread."""

from __future__ import annotations

import threading
import time

import pytest

from services.solver.optimize.background import BackgroundReporter


class Host:
    """Records each report with the thread that wrote it; ``fail_on`` raises on that report."""

    def __init__(self, fail_on: str | None = None, delay: float = 0.0):
        self.seen: list[tuple[str, object, str]] = []
        self.fail_on, self.delay = fail_on, delay

    def _got(self, name, value):
        time.sleep(self.delay)
        if name == self.fail_on:
            raise OSError(f"store full at {name}")
        self.seen.append((name, value, threading.current_thread().name))

    def plan(self, plan):
        self._got("plan", plan)

    def targets(self, images):
        self._got("targets", images)

    def progress(self, kind, payload):
        self._got("progress", kind)

    def iteration(self, record, renders, gradients, silhouettes=None):
        self._got("iteration", record)

    def checkpoint(self, state, next_iteration):
        self._got("checkpoint", next_iteration)

    def should_stop(self):
        return None

    def images_requested(self):
        return False


def test_reports_arrive_in_order_on_the_writer_thread_and_a_checkpoint_waits():
    host = Host(delay=0.01)
    reports = BackgroundReporter(host)
    reports.plan({"a": 1})
    for k in range(5):
        reports.iteration(k, None, None)
    reports.checkpoint(b"state", 5)
    # the checkpoint returned: it and everything before it are written
    assert [(n, v) for n, v, _ in host.seen] == [("plan", {"a": 1})] + [("iteration", k) for k in range(5)] + [
        ("checkpoint", 5)]
    assert {thread for _, _, thread in host.seen} == {"run-reports"}
    reports.iteration(5, None, None)
    reports.close()
    assert host.seen[-1][:2] == ("iteration", 5)


def test_a_writer_failure_is_raised_on_the_loop_thread_and_later_reports_are_dropped():
    host = Host(fail_on="iteration")
    reports = BackgroundReporter(host)
    reports.plan({})
    reports.iteration(0, None, None)
    with pytest.raises(OSError, match="store full"):
        reports.flush()
    with pytest.raises(OSError, match="store full"):   # every later report says so too
        reports.progress("warmup", {})
    reports.close()                                    # already seen by the loop: not raised again
    assert [n for n, _, _ in host.seen] == ["plan"]


def test_close_raises_a_failure_the_loop_never_saw():
    reports = BackgroundReporter(Host(fail_on="progress"))
    reports.progress("warmup", {})
    with pytest.raises(OSError):
        reports.close()


def test_depth_is_checked():
    with pytest.raises(ValueError, match="depth"):
        BackgroundReporter(Host(), depth=0)


def test_the_switch_interval_is_short_while_the_writer_runs_and_restored_after():
    import sys

    from services.solver.optimize.background import SWITCH_INTERVAL

    before = sys.getswitchinterval()
    reporter = BackgroundReporter(Host())
    try:
        assert sys.getswitchinterval() <= SWITCH_INTERVAL < before
    finally:
        reporter.close()
    assert sys.getswitchinterval() == before

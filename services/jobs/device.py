"""The device this machine's children run on, as they resolve it.

``NDRF_DEVICE`` (``auto``, ``cpu`` or ``cuda``: :class:`services.settings.Settings`) is passed to
every child; the child resolves it with :func:`services.solver.backend.device` (the API and the
worker never import Mitsuba or torch). :class:`DeviceReport` asks one ``device`` child, once per
process and in the background, what that gives here, for ``/healthz``, ``/metrics`` and a worker's
start-up log line. Each job's ``plan.json`` names the device its own child ran on.
"""

from __future__ import annotations

import logging
import tempfile
import threading
from collections.abc import Callable
from pathlib import Path

log = logging.getLogger(__name__)

#: Seconds a device child may take (imports, the CUDA driver's start).
PROBE_SECONDS = 120.0


def probe_device() -> dict:
    """Run one ``device`` child and return its answer (:meth:`services.solver.backend.Device.to_json`);
    a child that fails gives ``{"device": "unavailable", "reason": ...}``."""
    from services.jobs.isolation import ChildFailed, ChildLimits, exchange
    from services.settings import get_settings

    requested = get_settings().device
    base = Path(tempfile.gettempdir()) / "ndrf-device"     # the sandbox hides the work folder's parent
    base.mkdir(exist_ok=True)
    try:
        with tempfile.TemporaryDirectory(dir=base) as work:
            kind, meta = exchange("device", {}, ChildLimits(wall_seconds=PROBE_SECONDS), Path(work), "the device probe")
    except ChildFailed as exc:
        return {"device": "unavailable", "requested": requested, "reason": str(exc)}
    if kind != "device":
        return {"device": "unavailable", "requested": requested, "reason": f"the device probe answered {kind}"}
    return meta


class DeviceReport:
    """The children's device, probed once in a background thread on first use."""

    def __init__(self, probe: Callable[[], dict] = probe_device, on_known: Callable[[dict], None] | None = None):
        self._probe, self._on_known = probe, on_known
        self._value: dict | None = None
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None

    def get(self) -> dict | None:
        """The device, or None while the probe runs (it is started by the first call)."""
        with self._lock:
            if self._thread is None:
                self._thread = threading.Thread(target=self._run, name="device-probe", daemon=True)
                self._thread.start()
            return self._value

    def wait(self, timeout: float | None = None) -> dict | None:
        self.get()
        assert self._thread is not None
        self._thread.join(timeout)
        return self._value

    def _run(self) -> None:
        try:
            value = self._probe()
        except Exception as exc:  # never take the process down for a report
            log.exception("device probe failed")
            value = {"device": "unavailable", "reason": f"{type(exc).__name__}: {exc}"}
        self._value = value
        if self._on_known is not None:
            self._on_known(value)

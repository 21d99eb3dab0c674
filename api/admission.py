"""Admission work of an API process, shared fairly between keys.

Scene checks (a job's preflight, an experiment's, a scene's parameters) and views run in sandboxed
children that take seconds each; the process runs at most ``NDRF_PREFLIGHT_WORKERS`` of them (and
the short blocking calls of the submit path) at once, on one shared limiter. Before, one key could
hold every slot of it (an experiment whose runs differ in ``render.spp``: one check per setting,
all in a row) and every other key's ``POST /v1/jobs`` waited behind it (75 s with 40 settings).

Here a key's work first takes a place in that key's own limiter (``NDRF_ADMISSION_PER_KEY``
places), and only then a slot of the shared one: a key's further work waits in its own line, not
in the shared one, so a key with no work in flight finds a free slot whenever the others use fewer
than all of them (with the defaults, 2 slots and 1 per key: always, against one busy key).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import anyio


class Admission:
    def __init__(self, shared: anyio.CapacityLimiter, per_key: int):
        self.shared, self.per_key = shared, per_key
        self._keys: dict[str, anyio.CapacityLimiter] = {}

    async def run(self, owner: str, fn: Callable[..., Any], *args: Any) -> Any:
        """``fn(*args)`` in a worker thread, once ``owner`` has a place of its own and a shared slot
        is free."""
        limiter = self._keys.get(owner)
        if limiter is None:
            limiter = self._keys[owner] = anyio.CapacityLimiter(self.per_key)
        try:
            async with limiter:
                return await anyio.to_thread.run_sync(fn, *args, limiter=self.shared)
        finally:
            stats = limiter.statistics()
            if stats.borrowed_tokens == 0 and stats.tasks_waiting == 0:
                self._keys.pop(owner, None)

    def in_flight(self, owner: str) -> int:
        """Admission work of ``owner`` running or waiting in this process."""
        limiter = self._keys.get(owner)
        if limiter is None:
            return 0
        stats = limiter.statistics()
        return stats.borrowed_tokens + stats.tasks_waiting

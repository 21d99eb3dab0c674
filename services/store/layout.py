"""One job folder, the same for the CLI and the service (the store is the source of truth).

    <job>/
      spec.json                     the job as submitted
      plan.json                     what actually runs: resolved settings, scalars, bounds, fields
      record.json                   status, iteration, attempt, error (rewritten atomically)
      events.jsonl                  append-only event log (one JSON object per line)
      targets/target-<s>.png|.npy   target image of sensor s
      iterations/<k>/record.json    loss, parameters, dz/dp, seconds per phase, residual norms
      iterations/<k>/render.png     candidate of sensor 0 (render-<s>.png for the others)
      iterations/<k>/gradients.npy  dI/dp of sensor 0, float32 (P, H, W, 3)
      iterations/<k>/gradient-<p>.png
      checkpoints/latest.pt         everything needed to continue (see services.optimize.checkpoint)
      summary.json                  final status, parameters, iterations, seconds

Every file is written atomically (services.store.files); the event log is appended line by line
and readers skip a torn last line.
"""

from __future__ import annotations

import json
import os
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, Iterator

from services.store.files import atomic_write_json, dumps, read_json


def now_iso() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="milliseconds")


class JobFolder:
    """Paths and small read/write helpers of one job folder."""

    def __init__(self, root: str | Path):
        self.root = Path(root)

    # ------------------------------------------------------------------ paths
    spec_path = property(lambda self: self.root / "spec.json")
    plan_path = property(lambda self: self.root / "plan.json")
    record_path = property(lambda self: self.root / "record.json")
    events_path = property(lambda self: self.root / "events.jsonl")
    summary_path = property(lambda self: self.root / "summary.json")
    checkpoint_path = property(lambda self: self.root / "checkpoints" / "latest.pt")

    def iteration_dir(self, k: int) -> Path:
        return self.root / "iterations" / f"{k:06d}"

    def target_path(self, sensor: int, ext: str) -> Path:
        return self.root / "targets" / f"target-{sensor}.{ext}"

    # ------------------------------------------------------------ documents
    def write(self, name: str, value: Any) -> None:
        atomic_write_json(self.root / name, value)

    def read(self, name: str, default: Any = None) -> Any:
        path = self.root / name
        return read_json(path) if path.is_file() else default

    def iterations(self) -> list[int]:
        """Iteration indices with a complete record, ascending."""
        folder = self.root / "iterations"
        if not folder.is_dir():
            return []
        return sorted(int(p.name) for p in folder.iterdir() if p.name.isdigit() and (p / "record.json").is_file())

    def iteration_record(self, k: int) -> dict | None:
        path = self.iteration_dir(k) / "record.json"
        return read_json(path) if path.is_file() else None

    def drop_iterations_after(self, k: int) -> None:
        """Forget records newer than iteration ``k`` (a resumed run recomputes them)."""
        for j in self.iterations():
            if j > k:
                (self.iteration_dir(j) / "record.json").unlink(missing_ok=True)

    # --------------------------------------------------------------- events
    def append_event(self, event: dict) -> dict:
        """Append one event (``seq`` and ``time`` are added) and return it."""
        event = {"seq": self._next_seq(), "time": now_iso(), **event}
        self.root.mkdir(parents=True, exist_ok=True)
        line = (dumps(event, indent=None) + "\n").encode()
        fd = os.open(self.events_path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        try:
            os.write(fd, line)
            os.fsync(fd)
        finally:
            os.close(fd)
        self._seq = event["seq"]
        return event

    def events(self, after: int = 0) -> Iterator[dict]:
        """Events with ``seq > after``; a torn last line (killed writer) is skipped."""
        if not self.events_path.is_file():
            return
        with self.events_path.open("rb") as handle:
            for raw in handle:
                try:
                    event = json.loads(raw)
                except json.JSONDecodeError:
                    continue
                if event.get("seq", 0) > after:
                    yield event

    def read_events(self, offset: int = 0) -> tuple[list[dict], int]:
        """Complete events written after byte ``offset`` and the offset to continue from (a reader
        tailing the log reads each byte once; a torn last line waits for its newline)."""
        if not self.events_path.is_file():
            return [], offset
        with self.events_path.open("rb") as handle:
            handle.seek(offset)
            data = handle.read()
        end = data.rfind(b"\n") + 1
        events = []
        for raw in data[:end].splitlines():
            try:
                events.append(json.loads(raw))
            except json.JSONDecodeError:
                continue
        return events, offset + end

    def _next_seq(self) -> int:
        if getattr(self, "_seq", None) is None:
            self._seq = max((e["seq"] for e in self.events()), default=0)
        return self._seq + 1

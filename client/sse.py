"""Server-Sent Events parsing (the subset the service sends: ``id``, ``event``, ``data``, comments)."""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator


def parse_stream(lines: Iterable[bytes]) -> Iterator[dict]:
    """The JSON ``data`` of every complete event of a byte-line stream; the SSE ``id`` is kept as
    ``seq`` when the data has none."""
    data: list[str] = []
    event_id = None
    for raw in lines:
        line = raw.decode("utf-8", errors="replace").rstrip("\r\n")
        if not line:
            if data:
                event = json.loads("\n".join(data))
                if isinstance(event, dict):
                    if event_id is not None:
                        event.setdefault("seq", int(event_id))
                    yield event
            data, event_id = [], None
            continue
        if line.startswith(":"):
            continue
        field, _, value = line.partition(":")
        value = value[1:] if value.startswith(" ") else value
        if field == "data":
            data.append(value)
        elif field == "id" and value.isdigit():
            event_id = value

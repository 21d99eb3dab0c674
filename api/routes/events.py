"""``GET /v1/jobs/{id}/events``: Server-Sent Events, one per iteration and per status change.

Every event carries its sequence number as the SSE ``id``; a client reconnecting with
``Last-Event-ID`` (or ``?after=``) gets everything it missed, replayed from the job's append-only
event log in the store, then live events as the event bus announces them. The stream ends after
the event that finishes the job.
"""

from __future__ import annotations

import asyncio
import json
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import StreamingResponse

from api.deps import Authenticated, RuntimeDep
from api.problems import Problem
from api.routes.jobs import folder_or_404
from schemas.records import FINISHED

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["events"], dependencies=[Authenticated],
                   responses={401: {"model": Problem}, 404: {"model": Problem}})

KEEPALIVE_SECONDS = 15.0


def sse(event: dict) -> str:
    return f"id: {event['seq']}\nevent: {event['type']}\ndata: {json.dumps(event, separators=(',', ':'))}\n\n"


def _finishes(event: dict) -> bool:
    return event.get("type") == "status" and event.get("status") in FINISHED


@router.get("/events", summary="Event stream (SSE)", responses={200: {"content": {"text/event-stream": {}}}})
async def job_events(job_id: str, request: Request, runtime: RuntimeDep,
                     last_event_id: Annotated[str | None, Header(alias="Last-Event-ID", pattern=r"^\d{1,12}$")] = None,
                     after: Annotated[int | None, Query(ge=0, description="Replay events after this id.")] = None):
    folder = folder_or_404(runtime, job_id)
    start = int(last_event_id) if last_event_id is not None else (after or 0)

    async def stream():
        sent, offset = start, 0
        yield "retry: 2000\n\n"
        while not await request.is_disconnected():
            events, offset = folder.read_events(offset)
            for event in events:
                if event.get("seq", 0) <= sent:
                    continue
                sent = event["seq"]
                yield sse(event)
                if _finishes(event) and folder.read("record.json", {}).get("status") in FINISHED:
                    return
            if not events and folder.read("record.json", {}).get("status") in FINISHED:
                return            # a client reconnecting after the end: nothing more will come
            woke = await asyncio.to_thread(runtime.events.wait, job_id, sent, KEEPALIVE_SECONDS)
            if not woke:
                yield ": keep-alive\n\n"

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

"""``GET /v1/jobs/{id}/events``: Server-Sent Events, one per iteration, per status change and per
warm-up progress report.

Every event carries its sequence number as the SSE ``id``; a client reconnecting with
``Last-Event-ID`` (or ``?after=``) gets everything it missed, replayed from the job's append-only
event log in the store, then live events from this process's feed of the job (:mod:`api.streams`:
one bus wait and one store read per job, whatever the number of clients). Nothing here holds a
thread while it waits. The stream ends after the event that finishes the job.

A key may hold ``NDRF_MAX_STREAMS_PER_KEY`` streams at once (429; 503 when the count cannot be read),
counted across every API process that shares the Redis, job and experiment streams together, those
opened with its read tokens included (:class:`api.streams.StreamSlot`).
"""

from __future__ import annotations

import asyncio
import json
from typing import Annotated

from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import StreamingResponse

from api.bodies import GuardedRoute
from api.deps import ReaderDep, RuntimeDep
from api.problems import ProblemDetails
from api.streams import END, StreamHub, StreamSlot, counted_owner, finishes

router = APIRouter(route_class=GuardedRoute, prefix="/v1/jobs/{job_id}", tags=["events"],
                   responses={401: {"model": ProblemDetails}, 404: {"model": ProblemDetails},
                              429: {"model": ProblemDetails}, 503: {"model": ProblemDetails}})

KEEPALIVE_SECONDS = 15.0


def sse(event: dict) -> str:
    return f"id: {event['seq']}\nevent: {event['type']}\ndata: {json.dumps(event, separators=(',', ':'))}\n\n"


@router.get("/events", summary="Event stream (SSE)", responses={200: {"content": {"text/event-stream": {}}}})
async def job_events(job_id: str, request: Request, runtime: RuntimeDep, caller: ReaderDep,
                     last_event_id: Annotated[str | None, Header(alias="Last-Event-ID", pattern=r"^\d{1,12}$")] = None,
                     after: Annotated[int | None, Query(ge=0, description="Replay events after this id.")] = None):
    hub: StreamHub = request.app.state.streams
    record = await hub.blocking(runtime.service.record, job_id, caller)
    start = int(last_event_id) if last_event_id is not None else (after or 0)
    slot = await StreamSlot.take(runtime, counted_owner(caller, record.owner))

    async def stream():
        sent = start
        try:
            yield "retry: 2000\n\n"
            async with hub.subscribe(job_id) as queue:
                replayed = await hub.replay(job_id, sent)
                for event in replayed:
                    if event["seq"] > sent:
                        sent = event["seq"]
                        yield sse(event)
                if any(finishes(e) for e in replayed) or (not replayed and await hub.finished(job_id)):
                    return
                while True:
                    try:
                        event = await asyncio.wait_for(queue.get(), KEEPALIVE_SECONDS)
                    except TimeoutError:
                        yield ": keep-alive\n\n"
                    else:
                        if event is END:
                            return
                        if event["seq"] > sent:
                            sent = event["seq"]
                            yield sse(event)
                    await slot.keep()
        finally:
            await slot.release()

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

"""``GET /v1/jobs/{id}/events``: Server-Sent Events, one per iteration, per status change and per
warm-up progress report.

Every event carries its sequence number as the SSE ``id``; a client reconnecting with
``Last-Event-ID`` (or ``?after=``) gets everything it missed, replayed from the job's append-only
event log in the store, then live events from this process's feed of the job (:mod:`api.streams`:
one bus wait and one store read per job, whatever the number of clients). Nothing here holds a
thread while it waits. The stream ends after the event that finishes the job.

A key may hold ``NDRF_MAX_STREAMS_PER_KEY`` streams at once (429), counted across every API process
that shares the Redis (:class:`services.queue.base.StreamSlots`).
"""

from __future__ import annotations

import asyncio
import json
import time
from typing import Annotated

import anyio
from fastapi import APIRouter, Header, Query, Request
from fastapi.responses import StreamingResponse

from api.bodies import GuardedRoute
from api.deps import ReaderDep, RuntimeDep, files_or_404
from api.problems import ProblemDetails, ProblemError
from api.streams import END, StreamHub, finishes

router = APIRouter(route_class=GuardedRoute, prefix="/v1/jobs/{job_id}", tags=["events"],
                   responses={401: {"model": ProblemDetails}, 404: {"model": ProblemDetails},
                              429: {"model": ProblemDetails}})

KEEPALIVE_SECONDS = 15.0


def sse(event: dict) -> str:
    return f"id: {event['seq']}\nevent: {event['type']}\ndata: {json.dumps(event, separators=(',', ':'))}\n\n"


@router.get("/events", summary="Event stream (SSE)", responses={200: {"content": {"text/event-stream": {}}}})
async def job_events(job_id: str, request: Request, runtime: RuntimeDep, caller: ReaderDep,
                     last_event_id: Annotated[str | None, Header(alias="Last-Event-ID", pattern=r"^\d{1,12}$")] = None,
                     after: Annotated[int | None, Query(ge=0, description="Replay events after this id.")] = None):
    hub: StreamHub = request.app.state.streams
    await hub.blocking(files_or_404, runtime, job_id, caller)
    start = int(last_event_id) if last_event_id is not None else (after or 0)
    owner, cap, slots = caller.owner, runtime.settings.limits.streams_per_key, runtime.slots
    assert slots is not None
    slot = await slots.acquire(owner, cap)
    if slot is None:
        raise ProblemError(429, "Too many streams", f"this key already holds {cap} event streams "
                                                    f"(NDRF_MAX_STREAMS_PER_KEY)",
                           slug="too-many-streams", headers={"Retry-After": "5"})

    async def stream():
        sent, refreshed = start, time.monotonic()
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
                    if time.monotonic() - refreshed > slots.ttl_seconds / 3:
                        refreshed = time.monotonic()
                        await slots.refresh(owner, slot)
        finally:
            with anyio.CancelScope(shield=True):
                await slots.release(owner, slot)

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

"""``/v1/experiments``: sweeps over a job's fields, run as ordinary jobs, compared side by side.

Every run of an experiment is checked before anything is stored (a ``422`` names the run and the
field: ``runs[3].learning_rate``); the runs are then admitted into the job queue by the
scheduler, at most ``max_concurrent`` at a time (:mod:`services.experiments.scheduler`). The GET
routes of one experiment accept ``?token=`` with its read token (EventSource, download links).
"""

from __future__ import annotations

import json
from typing import Annotated

from fastapi import APIRouter, Depends, Header, Query, Request, Response
from fastapi.responses import PlainTextResponse, StreamingResponse

from api import tokens
from api.bodies import GuardedRoute
from api.deps import RuntimeDep, SettingsDep, may_mint_token, reader_of, require_caller
from api.problems import ProblemDetails, ProblemError, conflict
from api.streams import StreamHub, StreamSlot, counted_owner
from schemas.experiments import (
    Curves,
    ExperimentAccepted,
    ExperimentAppend,
    ExperimentPage,
    ExperimentPublic,
    ExperimentRecord,
    ExperimentSpec,
    RunRow,
)
from schemas.job import JobSpec
from services.experiments.expand import InvalidExperiment
from services.experiments.service import TooManyExperiments
from services.jobs.preflight import preflight
from services.jobs.service import Caller
from services.jobs.state import UnknownJob
from services.runtime import Runtime
from services.settings import Settings
from services.store.job import JobFiles

router = APIRouter(prefix="/v1/experiments", tags=["experiments"], route_class=GuardedRoute,
                   responses={401: {"model": ProblemDetails, "description": "Missing or wrong API key."}})

CallerDep = Annotated[Caller, Depends(require_caller)]
KEEPALIVE_SECONDS = 15.0
EXPERIMENT_PATTERN = "^e[0-9a-f]{20}$"


def require_experiment_reader(request: Request, settings: SettingsDep, exp_id: str) -> Caller:
    """A bearer key, or (GET only) a read token of this very experiment."""
    return reader_of(request, settings, exp_id)


ReaderDep = Annotated[Caller, Depends(require_experiment_reader)]


def _invalid(exc: InvalidExperiment) -> ProblemError:
    return ProblemError(422, "Invalid experiment", str(exc), slug="invalid-experiment",
                        errors=[(exc.field, exc.message)])


def _token(settings: Settings, exp_id: str) -> str | None:
    return tokens.sign(settings.signing_secret(), exp_id, settings.token_seconds) if settings.auth else None


def _accepted(response: Response, record: ExperimentRecord, added: list[int]) -> ExperimentAccepted:
    base = f"/v1/experiments/{record.id}"
    response.headers["Location"] = base
    return ExperimentAccepted(id=record.id, status=record.status, runs=len(record.runs), added=added,
                              links={"self": base, "runs": f"{base}/runs", "results": f"{base}/results.csv",
                                     "curves": f"{base}/curves", "events": f"{base}/events",
                                     "cancel": f"{base}/cancel", "retry": f"{base}/retry"})


@router.post("", status_code=202, response_model=ExperimentAccepted,
             responses={413: {"model": ProblemDetails}, 422: {"model": ProblemDetails}, 429: {"model": ProblemDetails}},
             summary="Create an experiment")
async def create_experiment(spec: ExperimentSpec, response: Response, runtime: RuntimeDep, caller: CallerDep):
    """Expand ``grid`` x ``samples`` random draws x ``seeds`` into runs, check every run as a job
    submission would be checked (schema, caps, the scene in a sandbox, once per distinct scene),
    and store the experiment; its runs are queued by the scheduler, ``max_concurrent`` at a time.
    A bad run is a ``422`` naming it and its field (``runs[3].learning_rate``); nothing is queued."""
    if spec.base_job is not None:
        spec = _with_base_of_job(runtime, spec, caller)

    def create():
        return runtime.experiments.create(spec, caller, preflight=preflight)

    try:
        record = await runtime.admission.run(caller.owner, create)
    except InvalidExperiment as exc:
        raise _invalid(exc) from None
    except TooManyExperiments as exc:
        raise ProblemError(429, "Too many experiments", str(exc), slug="too-many-experiments",
                           headers={"Retry-After": "60"}) from None
    return _accepted(response, record, [run.index for run in record.runs])


def _with_base_of_job(runtime: Runtime, spec: ExperimentSpec, caller: Caller) -> ExperimentSpec:
    """``base_job``: the job file of a job the caller may see."""
    try:
        document = runtime.service.files(spec.base_job or "", caller).read(JobFiles.SPEC)
    except UnknownJob:
        document = None
    if document is None:
        raise _invalid(InvalidExperiment("base_job", f"no job {spec.base_job!r}"))
    return spec.model_copy(update={"base": JobSpec.model_validate(document)})


@router.get("", response_model=ExperimentPage, summary="List experiments")
def list_experiments(runtime: RuntimeDep, settings: SettingsDep, caller: CallerDep,
                     limit: Annotated[int, Query(ge=1, le=200, description="Page size.")] = 50,
                     cursor: Annotated[str | None, Query(pattern=EXPERIMENT_PATTERN,
                                                         description="From a previous page.")] = None):
    """The caller's experiments (all of them for an admin key), newest first, with their progress
    (counts by status; the best run and aggregates are on the experiment's own page)."""
    items: list[ExperimentPublic] = []
    next_cursor = None
    for record in runtime.experiments.records(caller, before=cursor):
        if len(items) == limit:
            next_cursor = items[-1].id
            break
        items.append(runtime.experiments.public(record, read_token=_token(settings, record.id), detail=False))
    return ExperimentPage(items=items, next_cursor=next_cursor)


@router.get("/{exp_id}", response_model=ExperimentPublic, responses={404: {"model": ProblemDetails}},
            summary="An experiment")
def get_experiment(exp_id: str, request: Request, runtime: RuntimeDep, settings: SettingsDep, caller: ReaderDep):
    """Status, counts by status, the best run by the objective so far, and the mean and spread
    over seeds of every configuration. A request with ``?token=`` gets no fresh read token."""
    record = runtime.experiments.record(exp_id, caller)
    token = _token(settings, exp_id) if may_mint_token(request) else None
    return runtime.experiments.public(record, read_token=token)


@router.get("/{exp_id}/runs", response_model=list[RunRow], responses={404: {"model": ProblemDetails}},
            summary="The runs")
def get_runs(exp_id: str, runtime: RuntimeDep, caller: ReaderDep):
    """One row per run: varied values, status, final loss, final parameter error (synthetic
    targets), compute and wall seconds, time to reach the experiment's target_error, iterations."""
    return runtime.experiments.rows(runtime.experiments.record(exp_id, caller))


@router.get("/{exp_id}/results.csv", response_class=PlainTextResponse, summary="The runs as CSV",
            responses={200: {"content": {"text/csv": {}}}, 404: {"model": ProblemDetails}})
def get_results_csv(exp_id: str, runtime: RuntimeDep, caller: ReaderDep):
    """The rows of ``/runs`` as CSV (one column per varied field)."""
    from services.experiments.results import results_csv

    text = results_csv(runtime.experiments.rows(runtime.experiments.record(exp_id, caller)))
    return PlainTextResponse(text, media_type="text/csv",
                             headers={"Content-Disposition": f'attachment; filename="{exp_id}-results.csv"'})


@router.get("/{exp_id}/curves", response_model=Curves, responses={404: {"model": ProblemDetails}},
            summary="Accuracy against time")
def get_curves(exp_id: str, runtime: RuntimeDep, caller: ReaderDep):
    """Parameter error and loss against compute seconds, per run and per configuration (mean over
    its seeds, with the spread): for a sweep over ``method``, every method's curve on this scene."""
    return runtime.experiments.curves(runtime.experiments.record(exp_id, caller))


@router.post("/{exp_id}/cancel", status_code=202, response_model=ExperimentPublic,
             responses={404: {"model": ProblemDetails}, 409: conflict("experiment-finished")}, summary="Cancel")
def cancel_experiment(exp_id: str, runtime: RuntimeDep, settings: SettingsDep, caller: CallerDep):
    """Cancel pending runs and the jobs of queued and running runs (they keep their artifacts).
    A finished experiment is a ``409``."""
    runtime.experiments.record(exp_id, caller)
    record = runtime.experiments.cancel(exp_id, caller)
    return runtime.experiments.public(record, read_token=_token(settings, exp_id), detail=False)


@router.post("/{exp_id}/retry", status_code=202, response_model=ExperimentAccepted,
             responses={404: {"model": ProblemDetails}, 409: conflict("nothing-to-retry")}, summary="Retry")
def retry_experiment(exp_id: str, response: Response, runtime: RuntimeDep, caller: CallerDep):
    """Re-queue the failed and canceled runs (each gets a new job); succeeded runs are not run
    again. ``409`` when there is nothing to retry."""
    runtime.experiments.record(exp_id, caller)
    record, again = runtime.experiments.retry(exp_id, caller)
    return _accepted(response, record, again)


@router.post("/{exp_id}/runs", status_code=202, response_model=ExperimentAccepted,
             responses={404: {"model": ProblemDetails}, 422: {"model": ProblemDetails}}, summary="Append runs")
async def append_runs(exp_id: str, more: ExperimentAppend, response: Response, runtime: RuntimeDep,
                      caller: CallerDep):
    """More values of the grid fields, more seeds or more random draws: the runs this adds are
    checked and queued; runs that exist are kept (finished ones are not run again). ``added`` is
    empty when nothing was new."""
    runtime.experiments.record(exp_id, caller)

    def append():
        return runtime.experiments.append(exp_id, more, caller, preflight=preflight)

    try:
        record, added = await runtime.admission.run(caller.owner, append)
    except InvalidExperiment as exc:
        raise _invalid(exc) from None
    return _accepted(response, record, added)


@router.get("/{exp_id}/events", summary="Event stream (SSE)",
            responses={200: {"content": {"text/event-stream": {}}}, 404: {"model": ProblemDetails},
                       429: {"model": ProblemDetails}, 503: {"model": ProblemDetails}})
async def experiment_events(exp_id: str, request: Request, runtime: RuntimeDep, caller: ReaderDep,
                            last_event_id: Annotated[str | None, Header(alias="Last-Event-ID",
                                                                        pattern=r"^\d{1,12}$")] = None,
                            after: Annotated[int | None, Query(ge=0, description="Replay events after this id.")]
                            = None):
    """``status`` (the experiment's), ``run`` (a run queued, running, finished: index, job,
    status), ``retry``, ``appended``, ``canceled``. Every event's SSE id is its sequence number;
    ``Last-Event-ID`` replays what was missed. The stream ends when the experiment finishes."""
    hub: StreamHub = request.app.state.streams
    record = await hub.blocking(runtime.experiments.record, exp_id, caller)
    states = runtime.experiments.states
    start = int(last_event_id) if last_event_id is not None else (after or 0)
    slot = await StreamSlot.take(runtime, counted_owner(caller, record.owner), "event streams")

    def finished() -> bool:
        return states.get(exp_id).status.finished

    async def stream():
        sent, cursor = start, None
        try:
            yield "retry: 2000\n\n"
            while not await request.is_disconnected():
                events, cursor = await hub.blocking(states.read_events, exp_id, sent, cursor)
                ended = False
                for event in events:
                    if event.get("seq", 0) <= sent:
                        continue
                    sent = event["seq"]
                    yield f"id: {sent}\nevent: {event['type']}\ndata: {json.dumps(event, separators=(',', ':'))}\n\n"
                    ended = ended or (event.get("type") == "status" and event.get("status") in FINAL)
                if (ended or not events) and await hub.blocking(finished):
                    return
                if not await runtime.events.wait_async(exp_id, sent, KEEPALIVE_SECONDS):
                    yield ": keep-alive\n\n"
                await slot.keep()
        finally:
            await slot.release()

    return StreamingResponse(stream(), media_type="text/event-stream",
                             headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})


FINAL = {"succeeded", "failed", "canceled"}

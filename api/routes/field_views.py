"""``/v1/jobs/{id}/views``: a job's fields rendered from a camera of the caller's choosing (paper
Fig. 4b), in a sandboxed child, and the files of each view."""

from __future__ import annotations

import base64
import re
from typing import Annotated

from fastapi import APIRouter
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, Response

from api.bodies import GuardedRoute
from api.deps import CallerDep, ReaderDep, RuntimeDep
from api.problems import ProblemDetails, ProblemError
from schemas.errors import InvalidJob
from schemas.views import ViewFiles, ViewRequest
from services.jobs.views import VIEW_FILE_PATTERN, VIEW_ID_PATTERN, NoCheckpoint, OverBudget, create_view

router = APIRouter(route_class=GuardedRoute, prefix="/v1/jobs/{job_id}/views", tags=["views"],
                   responses={401: {"model": ProblemDetails}, 404: {"model": ProblemDetails}})

MEDIA = {"png": "image/png", "npy": "application/x-npy", "json": "application/json"}


def _url(job_id: str, view_id: str, name: str) -> str:
    return f"/v1/jobs/{job_id}/views/{view_id}/{name}"


@router.post("", status_code=201, response_model=ViewFiles,
             responses={409: {"model": ProblemDetails}, 422: {"model": ProblemDetails}},
             summary="Render the job's fields from a camera")
async def create(job_id: str, request: ViewRequest, runtime: RuntimeDep, caller: CallerDep):
    """Render ``L_phi`` and every scalar's ``dL_theta`` at the first hits of the camera's rays, from
    the job's latest checkpoint (a running job's too), and ``prb``'s gradient image from the same
    camera when ``prb_spp`` is set. A job's checkpoint is restored once in a warm sandboxed child
    kept for ``NDRF_VIEW_KEEP_SECONDS`` after its last view (the next views skip the child's start);
    ``inline`` answers the PNGs in the response and stores nothing. Concurrent views of one
    checkpoint are serialized on its warm child (each waits its turn; none is refused or a
    ``500``). A job without a checkpoint yet, or whose method trains no
    field, or whose files would exceed the job's disk budget, is a ``409``; a camera that cannot be
    built a ``422``."""
    owner = runtime.service.record(job_id, caller).owner   # the warm child belongs to the job's key
    files = runtime.service.files(job_id, caller)
    try:
        view_id, written, meta = await runtime.admission.run(caller.owner, create_view, files, request,
                                                             runtime.settings.limits, runtime.view_sessions, owner)
    except NoCheckpoint as exc:
        raise ProblemError(409, "Conflict", str(exc), slug="no-checkpoint") from None
    except OverBudget as exc:
        raise ProblemError(409, "Conflict", str(exc), slug="job-budget") from None
    except InvalidJob as exc:
        status = 409 if "trained no field" in exc.message else 422
        raise ProblemError(status, "Invalid view", str(exc), slug="invalid-view",
                           errors=[(exc.field, exc.message)]) from None
    if request.inline:
        images = {name: "data:image/png;base64," + base64.b64encode(data).decode() for name, data in written.items()}
        files_ = {}
    else:
        images, files_ = {}, {name: _url(job_id, view_id, name) for name in sorted(written)}
    return ViewFiles(id=view_id, files=files_, images=images, scalars=meta.get("scalars", []),
                     seconds=meta.get("seconds", {}), iteration=meta.get("iteration"), camera=meta.get("camera") or {},
                     warm=bool(meta.get("warm")))


@router.get("/{view_id}/{name}", summary="A file of a view",
            responses={200: {"content": {media: {} for media in MEDIA.values()}}})
def view_file(job_id: str, runtime: RuntimeDep, caller: ReaderDep,
              view_id: Annotated[str, PathParam(pattern=VIEW_ID_PATTERN, description="The view's id.")],
              name: Annotated[str, PathParam(pattern=VIEW_FILE_PATTERN, description="A file the view wrote.")]):
    files = runtime.service.files(job_id, caller)
    key = files.key(f"views/{view_id}/{name}")
    media = MEDIA[re.sub(r".*\.", "", name)]
    path = files.store.local_path(key)
    if path is not None:
        return FileResponse(path, media_type=media)
    data = files.store.get(key)
    if data is None:
        raise ProblemError(404, "Not found", f"view {view_id} has no file {name}", slug="missing-artifact")
    return Response(data, media_type=media)

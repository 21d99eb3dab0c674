"""Per-iteration records and files of a job: gradient images, renders, targets, checkpoints."""

from __future__ import annotations

import io
import re
from typing import Annotated

import numpy as np
from fastapi import APIRouter, Path as PathParam, Query
from fastapi.responses import FileResponse, Response

from api.deps import Authenticated, RuntimeDep
from api.problems import Problem, ProblemError
from api.routes.jobs import folder_or_404
from schemas.records import IterationRecord

router = APIRouter(prefix="/v1/jobs/{job_id}", tags=["artifacts"], dependencies=[Authenticated],
                   responses={401: {"model": Problem}, 404: {"model": Problem}})

Iteration = Annotated[int, PathParam(ge=0, le=10**7, description="0-based iteration index.")]
PNG, NPY = "image/png", "application/x-npy"


def _missing(what: str) -> ProblemError:
    return ProblemError(404, "Not found", f"{what} does not exist (yet)", slug="missing-artifact")


@router.get("/iterations", response_model=list[IterationRecord], summary="Iteration records",
            responses={200: {"headers": {"X-Last-Event-ID": {
                "description": "Sequence number of the job's last event when the records were read: follow "
                               "the event stream with ?after=<it> (an iteration listed here may be sent again).",
                "schema": {"type": "integer"}}}}})
def iterations(job_id: str, runtime: RuntimeDep, response: Response,
               after: Annotated[int, Query(ge=-1, description="Only iterations with a larger index.")] = -1):
    """Loss, parameters, dz/dp, seconds per phase and residual norms of every completed iteration."""
    folder = folder_or_404(runtime, job_id)
    events, _ = folder.read_events(0)    # before the records: each record is written before its event
    response.headers["X-Last-Event-ID"] = str(events[-1].get("seq", 0) if events else 0)
    return [folder.iteration_record(k) for k in folder.iterations() if k > after]


@router.get("/iterations/{k}/render.png", response_class=FileResponse, summary="Candidate render",
            responses={200: {"content": {PNG: {}}}})
def render_png(job_id: str, k: Iteration, runtime: RuntimeDep,
               sensor: Annotated[int, Query(ge=0, le=64, description="Sensor index.")] = 0):
    path = folder_or_404(runtime, job_id).iteration_dir(k) / ("render.png" if sensor == 0 else f"render-{sensor}.png")
    if not path.is_file():
        raise _missing(f"render of iteration {k}")
    return FileResponse(path, media_type=PNG)


_GRADIENT = re.compile(r"^(\d{1,4})\.(png|npy)$")


@router.get("/iterations/{k}/gradients/{name}", summary="Gradient image of one scalar",
            responses={200: {"content": {PNG: {}, NPY: {}}}})
def gradient(job_id: str, k: Iteration, runtime: RuntimeDep,
             name: Annotated[str, PathParam(description="'<p>.png' (preview, diverging colour map) or '<p>.npy' "
                                                        "(float32 H x W x 3) for scalar p.")]):
    match = _GRADIENT.match(name)
    if match is None:
        raise ProblemError(422, "Invalid request", "name must be '<scalar index>.png' or '<scalar index>.npy'",
                           slug="invalid-request", errors=[("name", "expected <p>.png or <p>.npy")])
    p, kind = int(match.group(1)), match.group(2)
    folder = folder_or_404(runtime, job_id).iteration_dir(k)
    if kind == "png":
        path = folder / f"gradient-{p}.png"
        if not path.is_file():
            raise _missing(f"gradient preview {p} of iteration {k}")
        return FileResponse(path, media_type=PNG)
    stack = folder / "gradients.npy"
    if not stack.is_file():
        raise _missing(f"gradient data of iteration {k}")
    images = np.load(stack, mmap_mode="r")
    if p >= images.shape[0]:
        raise _missing(f"scalar {p} (the job has {images.shape[0]})")
    buffer = io.BytesIO()
    np.save(buffer, np.ascontiguousarray(images[p]))
    return Response(buffer.getvalue(), media_type=NPY,
                    headers={"Content-Disposition": f'attachment; filename="{job_id}-{k}-{p}.npy"'})


@router.get("/iterations/{k}/gradients.npy", summary="All gradient images of an iteration",
            responses={200: {"content": {NPY: {}}}})
def gradients_stack(job_id: str, k: Iteration, runtime: RuntimeDep):
    path = folder_or_404(runtime, job_id).iteration_dir(k) / "gradients.npy"
    if not path.is_file():
        raise _missing(f"gradient data of iteration {k}")
    return FileResponse(path, media_type=NPY, filename=f"{job_id}-{k}-gradients.npy")


@router.get("/targets/{sensor}.png", summary="Target image", responses={200: {"content": {PNG: {}}}})
def target_png(job_id: str, runtime: RuntimeDep, sensor: Annotated[int, PathParam(ge=0, le=64)]):
    path = folder_or_404(runtime, job_id).target_path(sensor, "png")
    if not path.is_file():
        raise _missing(f"target of sensor {sensor}")
    return FileResponse(path, media_type=PNG)


@router.get("/checkpoints/latest", summary="Latest checkpoint", responses={200: {"content": {"application/octet-stream": {}}}})
def latest_checkpoint(job_id: str, runtime: RuntimeDep):
    """The torch checkpoint (fields, optimizers, parameters, Adam state, RNG, next iteration)."""
    path = folder_or_404(runtime, job_id).checkpoint_path
    if not path.is_file():
        raise _missing("a checkpoint")
    return FileResponse(path, media_type="application/octet-stream", filename=f"{job_id}-checkpoint.pt")

"""Per-iteration records and files of a job: gradient images, renders, targets, checkpoints.

Files are streamed from the store (a folder's file is sent as it is; other stores are read in
chunks, or redirected to a pre-signed URL when the store is configured so), never read whole into
memory; one scalar's gradient image is read as a byte range of the stack.
"""

from __future__ import annotations

import io
import re
from typing import Annotated

import numpy as np
import numpy.lib.format as npy_format
from fastapi import APIRouter, Query
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, RedirectResponse, Response, StreamingResponse

from api.bodies import GuardedRoute
from api.deps import ReaderDep, RuntimeDep
from api.problems import ProblemDetails, ProblemError
from schemas.records import IterationRecord
from services.store.job import JobFiles

router = APIRouter(route_class=GuardedRoute, prefix="/v1/jobs/{job_id}", tags=["artifacts"],
                   responses={401: {"model": ProblemDetails}, 404: {"model": ProblemDetails}})

Iteration = Annotated[int, PathParam(ge=0, le=10**7, description="0-based iteration index.")]
PNG, NPY, EXR, PLY, JSON = "image/png", "application/x-npy", "image/x-exr", "application/x-ply", "application/json"
CHUNK = 1 << 16


def _missing(what: str) -> ProblemError:
    return ProblemError(404, "Not found", f"{what} does not exist (yet)", slug="missing-artifact")


def send(files: JobFiles, key: str, media_type: str, what: str, filename: str | None = None):
    """Stream one object of the store (or redirect to a pre-signed URL of it)."""
    store = files.store
    path = store.local_path(key)
    if path is not None:
        return FileResponse(path, media_type=media_type, filename=filename)
    url = store.redirect_url(key)
    if url is not None:
        return RedirectResponse(url, status_code=307)
    handle = store.open(key)
    if handle is None:
        raise _missing(what)

    def chunks():
        with handle:
            while block := handle.read(CHUNK):
                yield block

    headers = {"Content-Disposition": f'attachment; filename="{filename}"'} if filename else None
    return StreamingResponse(chunks(), media_type=media_type, headers=headers)


@router.get("/iterations", response_model=list[IterationRecord], summary="Iteration records",
            responses={200: {"headers": {"X-Last-Event-ID": {
                "description": "Sequence number of the job's last event when the records were read: follow "
                               "the event stream with ?after=<it> (an iteration listed here may be sent again).",
                "schema": {"type": "integer"}}}}})
def iterations(job_id: str, runtime: RuntimeDep, response: Response, caller: ReaderDep,
               after: Annotated[int, Query(ge=-1, description="Only iterations with a larger index.")] = -1):
    """Loss, parameters, dz/dp, seconds per phase and residual norms of every completed iteration."""
    files = runtime.service.files(job_id, caller)
    events, _ = files.store.read_events(files.prefix)    # before the records: each record precedes its event
    response.headers["X-Last-Event-ID"] = str(events[-1].get("seq", 0) if events else 0)
    return [files.iteration_record(k) for k in files.iterations() if k > after]


@router.get("/iterations/{k}/render.png", summary="Candidate render", responses={200: {"content": {PNG: {}}}})
def render_png(job_id: str, k: Iteration, runtime: RuntimeDep, caller: ReaderDep,
               sensor: Annotated[int, Query(ge=0, le=64, description="Sensor index.")] = 0):
    files = runtime.service.files(job_id, caller)
    key = files.iteration_key(k, "render.png" if sensor == 0 else f"render-{sensor}.png")
    if not files.store.exists(key):
        raise _missing(f"render of iteration {k}")
    return send(files, key, PNG, f"render of iteration {k}")


@router.get("/iterations/{k}/silhouette.png", summary="Silhouettes of a geometry job",
            responses={200: {"content": {PNG: {}}}})
def silhouette_png(job_id: str, k: Iteration, runtime: RuntimeDep, caller: ReaderDep,
                   sensor: Annotated[int, Query(ge=0, le=64, description="Sensor index.")] = 0):
    """The moved shapes' silhouette at iteration ``k`` (orange) over the target in grey, with the
    target's silhouette outlined (cyan) when the target's values are known; written with the
    renders, for jobs with pose parameters only."""
    files = runtime.service.files(job_id, caller)
    key = files.iteration_key(k, "silhouette.png" if sensor == 0 else f"silhouette-{sensor}.png")
    if not files.store.exists(key):
        raise _missing(f"silhouette of iteration {k}")
    return send(files, key, PNG, f"silhouette of iteration {k}")


_GRADIENT = re.compile(r"^(\d{1,4})\.(png|npy)$")


@router.get("/iterations/{k}/gradients/{name}", summary="Gradient image of one scalar",
            responses={200: {"content": {PNG: {}, NPY: {}}}})
def gradient(job_id: str, k: Iteration, runtime: RuntimeDep, caller: ReaderDep,
             name: Annotated[str, PathParam(description="'<p>.png' (preview, diverging colour map) or '<p>.npy' "
                                                        "(float32 H x W x 3) for scalar p.")]):
    match = _GRADIENT.match(name)
    if match is None:
        raise ProblemError(422, "Invalid request", "name must be '<scalar index>.png' or '<scalar index>.npy'",
                           slug="invalid-request", errors=[("name", "expected <p>.png or <p>.npy")])
    p, kind = int(match.group(1)), match.group(2)
    files = runtime.service.files(job_id, caller)
    if kind == "png":
        key = files.iteration_key(k, f"gradient-{p}.png")
        if not files.store.exists(key):
            raise _missing(f"gradient preview {p} of iteration {k}")
        return send(files, key, PNG, f"gradient preview {p}")
    key = files.iteration_key(k, "gradients.npy")
    image = _stack_slice(files, key, p)
    if image is None:
        raise _missing(f"gradient data of iteration {k}")
    if isinstance(image, int):
        raise _missing(f"scalar {p} (the job has {image})")
    buffer = io.BytesIO()
    np.save(buffer, image)
    return Response(buffer.getvalue(), media_type=NPY,
                    headers={"Content-Disposition": f'attachment; filename="{job_id}-{k}-{p}.npy"'})


def _stack_slice(files: JobFiles, key: str, p: int) -> np.ndarray | int | None:
    """Image ``p`` of the ``(P, H, W, 3)`` stack ``key``, read as one byte range after the .npy
    header; the stack's length P when ``p`` is out of range; None when there is no stack."""
    head = files.store.get_range(key, 0, 4096)
    if head is None:
        return None
    stream = io.BytesIO(head)
    version = npy_format.read_magic(stream)
    reader = {(1, 0): npy_format.read_array_header_1_0, (2, 0): npy_format.read_array_header_2_0}.get(version)
    if reader is None:
        raise ProblemError(500, "Unreadable artifact", f"unsupported .npy version {version}", slug="unreadable-artifact")
    shape, fortran, dtype = reader(stream)
    if fortran or dtype.hasobject or len(shape) < 1:
        raise ProblemError(500, "Unreadable artifact", "the gradient stack is not a C-ordered numeric array",
                           slug="unreadable-artifact")
    if p >= shape[0]:
        return int(shape[0])
    count = int(np.prod(shape[1:]))
    data = files.store.get_range(key, stream.tell() + p * count * dtype.itemsize, count * dtype.itemsize)
    if data is None or len(data) != count * dtype.itemsize:
        return None
    return np.frombuffer(data, dtype=dtype).reshape(shape[1:])


@router.get("/iterations/{k}/gradients.npy", summary="All gradient images of an iteration",
            responses={200: {"content": {NPY: {}}}})
def gradients_stack(job_id: str, k: Iteration, runtime: RuntimeDep, caller: ReaderDep):
    files = runtime.service.files(job_id, caller)
    key = files.iteration_key(k, "gradients.npy")
    if not files.store.exists(key):
        raise _missing(f"gradient data of iteration {k}")
    return send(files, key, NPY, f"gradient data of iteration {k}", filename=f"{job_id}-{k}-gradients.npy")


#: ``<key>.npy|exr|png`` or ``<key>.dz_dp.npy|exr|png`` of a texture parameter (Mitsuba keys: letters, digits,
#: ``_.-``).
_TEXTURE = re.compile(r"^([A-Za-z0-9_][A-Za-z0-9_.\-]{0,255})\.(png|npy|exr|ply)$")
_TEXTURE_MEDIA = {"png": PNG, "npy": NPY, "exr": EXR, "ply": PLY}
#: ``<shape id>.ply`` of an optimized mesh (the id as the writer names files: letters, digits, ``_-``).
_MESH = re.compile(r"^([A-Za-z0-9_~-]{1,255})\.ply$")  # schemas.files.mesh_name
TextureName = Annotated[str, PathParam(description="'<key>.npy' (float32 H x W x C), '<key>.exr' (the same values, "
                                                   "OpenEXR 32-bit float) or '<key>.png' (preview) of a texture "
                                                   "parameter, e.g. 'wall.reflectance.data.npy'; per iteration also "
                                                   "'<key>.dz_dp.npy|exr|png', its gradient; at the end also "
                                                   "'<shape id>.ply', a shape parameter's recovered mesh.")]


def _texture(files: JobFiles, k: int | None, name: str):
    match = _TEXTURE.match(name)
    if match is None or ".." in name:
        raise ProblemError(422, "Invalid request", "name must be '<texture key>.npy', '.exr' or '.png' (or "
                                                   "'<shape id>.ply')", slug="invalid-request",
                           errors=[("name", "expected <key>.npy, <key>.exr, <key>.png or <shape id>.ply")])
    key = files.texture_key(k, match.group(1)) + "." + match.group(2)
    what = f"texture {match.group(1)}" + ("" if k is None else f" of iteration {k}")
    if not files.store.exists(key):
        raise _missing(what)
    return send(files, key, _TEXTURE_MEDIA[match.group(2)], what, filename=None if match.group(2) == "png" else name)


@router.get("/final/poses.json", summary="Recovered poses", responses={200: {"content": {JSON: {}}}})
def final_poses(job_id: str, runtime: RuntimeDep, caller: ReaderDep):
    """A pose job's recovered poses, per shape: the translation, the angles, the 4x4 ``matrix``
    (applied on top of the scene file's ``to_world``) and ``xml``, the ``<transform>`` to paste
    back into the scene (written at the end)."""
    files = runtime.service.files(job_id, caller)
    return send(files, files.key("final/poses.json"), JSON, "recovered poses", filename="poses.json")


@router.get("/final/{name}", summary="A recovered texture or mesh",
            responses={200: {"content": {PNG: {}, NPY: {}, EXR: {}, PLY: {}}}})
def final_texture(job_id: str, runtime: RuntimeDep, caller: ReaderDep, name: TextureName):
    """A texture parameter's recovered value, or a shape parameter's recovered mesh as PLY (written
    at the end; summary.json names the files)."""
    return _texture(runtime.service.files(job_id, caller), None, name)


@router.get("/iterations/{k}/textures/{name}", summary="A texture at an iteration",
            responses={200: {"content": {PNG: {}, NPY: {}, EXR: {}}}})
def iteration_texture(job_id: str, k: Iteration, runtime: RuntimeDep, caller: ReaderDep, name: TextureName):
    """A texture parameter at iteration ``k`` and its gradient (written with the iteration's images)."""
    return _texture(runtime.service.files(job_id, caller), k, name)


@router.get("/iterations/{k}/meshes/{name}", summary="A mesh at an iteration",
            responses={200: {"content": {PLY: {}}}})
def iteration_mesh(job_id: str, k: Iteration, runtime: RuntimeDep, caller: ReaderDep,
                   name: Annotated[str, PathParam(description="'<shape id>.ply': a shape parameter's mesh at the "
                                                              "iteration (written with its images).")]):
    """A shape parameter's mesh at iteration ``k``, binary PLY (written with the iteration's images)."""
    files = runtime.service.files(job_id, caller)
    if _MESH.match(name) is None:
        raise ProblemError(422, "Invalid request", "name must be '<shape id>.ply'", slug="invalid-request",
                           errors=[("name", "expected <shape id>.ply")])
    key = files.iteration_key(k, f"meshes/{name}")
    if not files.store.exists(key):
        raise _missing(f"mesh {name} of iteration {k}")
    return send(files, key, PLY, f"mesh {name} of iteration {k}", filename=f"{job_id}-{k}-{name}")


Sensor = Annotated[int, PathParam(ge=0, le=64, description="Sensor index.")]


def _target(files: JobFiles, sensor: int, ext: str, media_type: str):
    key = files.target_key(sensor, ext)
    if not files.store.exists(key):
        raise _missing(f"target of sensor {sensor}" + ("" if ext == "png" else f" as .{ext}"))
    return send(files, key, media_type, f"target of sensor {sensor}",
                filename=None if ext == "png" else f"{files.job_id}-target-{sensor}.{ext}")


@router.get("/targets/{sensor}.png", summary="Target image", responses={200: {"content": {PNG: {}}}})
def target_png(job_id: str, runtime: RuntimeDep, caller: ReaderDep, sensor: Sensor):
    """The target of a sensor as an sRGB preview."""
    return _target(runtime.service.files(job_id, caller), sensor, "png", PNG)


@router.get("/targets/{sensor}.exr", summary="Target image as OpenEXR", responses={200: {"content": {EXR: {}}}})
def target_exr(job_id: str, runtime: RuntimeDep, caller: ReaderDep, sensor: Sensor):
    """The target of a sensor, linear RGB as fitted (OpenEXR, 32-bit float, unclamped)."""
    return _target(runtime.service.files(job_id, caller), sensor, "exr", EXR)


@router.get("/checkpoints/latest", summary="Latest checkpoint",
            responses={200: {"content": {"application/octet-stream": {}}}})
def latest_checkpoint(job_id: str, runtime: RuntimeDep, caller: ReaderDep):
    """The torch checkpoint (fields, optimizers, parameters, Adam state, RNG, next iteration)."""
    files = runtime.service.files(job_id, caller)
    key = files.key(JobFiles.CHECKPOINT)
    if not files.store.exists(key):
        raise _missing("a checkpoint")
    return send(files, key, "application/octet-stream", "a checkpoint", filename=f"{job_id}-checkpoint.pt")

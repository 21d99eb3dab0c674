"""Views of a job's fields on the host: the job's checkpoint handed to a sandboxed child that
renders the camera (``services.jobs.child`` mode ``view``), and the files of a view.

A view's files (under ``views/<id>/`` of the job in the store, or ``ndrf view``'s ``--out``):

    radiance.npy / .png       E + L_phi at the first hits, float32 (H, W, 3), PNG in sRGB
    gradients.npy             dL_theta (+ dE) per scalar, float32 (P, H, W, 3)
    gradient-<p>.png          scalar p's image in the dashboard's diverging map
    prb.npy, prb-<p>.png      prb's gradient images from the same camera (when asked), each PNG at
                              the scale of the field's image of the same scalar (side by side)
    view.json                 the request, the camera, the scalars, seconds, the checkpoint's iteration
"""

from __future__ import annotations

import json
import secrets
import tempfile
from pathlib import Path

import numpy as np

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.views import ViewRequest
from services.jobs.frames import array_from
from services.jobs.isolation import ChildFailed, ChildLimits, exchange_frame
from services.jobs.preflight import checks_folder, public_message, upload_limits
from services.jobs.view_sessions import ViewSessions
from services.settings import Limits
from services.store.images import gradient_png, npy_bytes, srgb_png
from services.store.job import JobFiles
from services.uploads.staging import stage_scene

#: A view's id: 12 hex digits.
VIEW_ID_PATTERN = r"^[0-9a-f]{12}$"
#: The names a view's files may have.
VIEW_FILE_PATTERN = r"^(radiance\.(npy|png)|gradients\.npy|prb\.npy|(gradient|prb)-\d{1,3}\.png|view\.json)$"


class NoCheckpoint(Exception):
    """The job has no checkpoint yet (no fields to view)."""


class OverBudget(Exception):
    """The view's files would take the job's files over their disk budget (``job_bytes``)."""


def view_files(radiance: np.ndarray, gradients: np.ndarray, prb: np.ndarray | None, meta: dict) -> dict[str, bytes]:
    """Every file of one view by name (module docstring)."""
    files = {"radiance.npy": npy_bytes(radiance.astype(np.float32)), "radiance.png": srgb_png(radiance),
             "gradients.npy": npy_bytes(gradients.astype(np.float32))}
    scales = {}
    for p, image in enumerate(gradients):
        files[f"gradient-{p}.png"], scales[p] = gradient_png(image)
    if prb is not None:
        files["prb.npy"] = npy_bytes(prb.astype(np.float32))
        for p, image in enumerate(prb):
            files[f"prb-{p}.png"], _ = gradient_png(image, scales[p] or None)
    files["view.json"] = json.dumps({**meta, "scales": scales}, indent=2).encode()
    return files


def check_view(request: ViewRequest, spec: JobSpec, limits: Limits) -> None:
    """Size a view before any child starts: its sides and spp within the service's caps
    (``NDRF_MAX_RESOLUTION``, ``NDRF_MAX_SPP``), its samples (width x height x spp, and x prb_spp)
    within ``NDRF_MAX_VIEW_SAMPLES``. A sensor's film not overridden is sized by the job's
    ``render.resolution``, else by the resolution cap."""
    width, height = request.resolution or spec.render.resolution or (limits.resolution, limits.resolution)
    if max(width, height) > limits.resolution:
        raise InvalidJob("resolution", f"{width} x {height} exceeds the largest side of {limits.resolution} pixels "
                                       f"(NDRF_MAX_RESOLUTION)")
    for field, spp in (("spp", request.spp), ("prb_spp", request.prb_spp)):
        if spp is None:
            continue
        if spp > limits.spp:
            raise InvalidJob(field, f"{spp} exceeds the limit of {limits.spp} samples per pixel (NDRF_MAX_SPP)")
        if width * height * spp > limits.view_samples:
            raise InvalidJob(field, f"{width} x {height} pixels x {spp} spp = {width * height * spp} samples exceed "
                                    f"the limit of {limits.view_samples} samples of one view (NDRF_MAX_VIEW_SAMPLES):"
                                    f" ask for fewer pixels or samples")


def view_limits(limits: Limits) -> ChildLimits:
    return ChildLimits(memory_bytes=limits.child_memory_bytes, cpu_seconds=int(limits.view_seconds) * 2,
                       wall_seconds=limits.view_seconds)


def _answer(kind: str, meta: dict, blobs: dict[str, bytes]) -> tuple[dict, dict[str, np.ndarray]]:
    if kind == "invalid":
        raise InvalidJob(str(meta.get("field", "view")), public_message(str(meta.get("message", "invalid"))))
    if kind != "viewed":
        raise InvalidJob("view", f"the view answered {kind!r}")
    arrays = {"radiance": array_from(blobs["radiance"], ndim=3), "gradients": array_from(blobs["gradients"], ndim=4)}
    if "prb" in blobs:
        arrays["prb"] = array_from(blobs["prb"], ndim=4)
    return meta, arrays


def render_in_child(spec: JobSpec, checkpoint: bytes, request: ViewRequest,
                    limits: Limits) -> tuple[dict, dict[str, np.ndarray]]:
    """Render the view in a sandboxed child; returns its description and its arrays. Raises
    :class:`InvalidJob` (field ``view``, or the scene's) when the view cannot be rendered."""
    with tempfile.TemporaryDirectory(prefix="ndrf-view-", dir=checks_folder()) as tmp:
        folder = Path(tmp)
        scene_file = stage_scene(spec.scene, folder / "scene", upload_limits(limits))
        (folder / "latest.pt").write_bytes(checkpoint)
        start = {"spec": spec.model_dump(mode="json"), "scene_file": str(scene_file) if scene_file else None,
                 "checkpoint_file": str(folder / "latest.pt"), "request": request.model_dump(mode="json")}
        try:
            kind, meta, blobs = exchange_frame("view", start, view_limits(limits), folder, "the view")
        except ChildFailed as exc:
            raise InvalidJob("view", public_message(str(exc))) from None
    return _answer(kind, meta, blobs)


def render_warm(sessions: ViewSessions, job_id: str, spec: JobSpec, checkpoint: bytes, request: ViewRequest,
                limits: Limits, owner: str = "") -> tuple[dict, dict[str, np.ndarray], bool]:
    """The view from this checkpoint's warm child (started if needed); ``(meta, arrays, warm)``
    where ``warm`` says an already running child answered. A warm child that died (or was closed,
    idle or evicted, while this request waited for it) is replaced once."""
    for _ in range(2):
        try:
            session, started = sessions.session(job_id, spec, checkpoint, limits, owner)
        except ChildFailed as exc:
            raise InvalidJob("view", public_message(str(exc))) from None
        try:
            kind, meta, blobs = session.view(request)
        except ChildFailed as exc:
            sessions.drop(session)
            if started and not session.retired:   # retired: closed under it before its view (evicted, replaced)
                raise InvalidJob("view", public_message(str(exc))) from None
            continue
        if (kind == "invalid" and started) or not session.kept:   # no child kept for it
            sessions.drop(session)
        meta, arrays = _answer(kind, meta, blobs)
        return meta, arrays, not started
    raise InvalidJob("view", "the view child ended twice")


def create_view(files: JobFiles, request: ViewRequest, limits: Limits, sessions: ViewSessions | None = None,
                owner: str = "") -> tuple[str, dict[str, bytes], dict]:
    """Render a view of the job of ``files`` (the caller has checked who may see it) from its latest
    checkpoint (in a warm child of ``sessions`` when given and enabled, else a one-off child) and,
    unless ``request.inline``, store its files under ``views/<id>/``; returns the id, the files
    and the view's description (``warm``: a warm child answered). Raises :class:`NoCheckpoint`,
    :class:`OverBudget` or :class:`InvalidJob`."""
    stored = files.read(JobFiles.SPEC)
    checkpoint = files.store.get(files.key(JobFiles.CHECKPOINT))
    if stored is None or checkpoint is None:
        raise NoCheckpoint(f"job {files.job_id} has no checkpoint yet: its fields are written with the first one")
    spec = JobSpec.model_validate(stored)
    check_view(request, spec, limits)
    warm = False
    if sessions is not None and sessions.enabled:
        meta, arrays, warm = render_warm(sessions, files.job_id, spec, checkpoint, request, limits, owner)
    else:
        meta, arrays = render_in_child(spec, checkpoint, request, limits)
    meta = {**meta, "request": request.model_dump(mode="json"), "warm": warm}
    view_id = secrets.token_hex(6)
    written = view_files(arrays["radiance"], arrays["gradients"], arrays.get("prb"), meta)
    if request.inline:
        return view_id, {name: data for name, data in written.items() if name.endswith(".png")}, meta
    size, used = sum(len(data) for data in written.values()), files.store.prefix_bytes(files.prefix)
    if used + size > limits.job_bytes:
        raise OverBudget(f"the view's {size} bytes would take the job's files over {limits.job_bytes} bytes "
                         f"(NDRF_MAX_JOB_BYTES; they hold {used}): delete the job's views or ask for a smaller one")
    for name, data in written.items():
        files.store.put(files.key(f"views/{view_id}/{name}"), data)
    return view_id, written, meta

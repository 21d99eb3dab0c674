"""Views of a job's fields on the host: the job's checkpoint handed to a sandboxed child that
renders the camera (``services.jobs.child`` mode ``view``), and the files of a view.

A view's files (under ``views/<id>/`` of the job in the store, or ``ndrf view``'s ``--out``):

    radiance.npy / .png       E + L_phi at the first hits, float32 (H, W, 3), PNG in sRGB
    gradients.npy             dL_theta (+ dE) per scalar, float32 (P, H, W, 3)
    gradient-<p>.png          scalar p's image in the dashboard's diverging map
    prb.npy, prb-<p>.png      prb's gradient images from the same camera (when asked), each PNG at
                              the scale of the field's image of the same scalar (side by side)
    view.json                 the request, the camera, the scalars, seconds, the checkpoint's iteration

The child writes the files but ``view.json`` into its work folder (:mod:`services.jobs.view_files`);
they are copied into the store file by file (``ArtifactStore.put_file``), or, ``inline``, only the
PNGs are read (each at most :data:`INLINE_PNG_BYTES`): a view's arrays never pass through the API's
memory.
"""

from __future__ import annotations

import os
import secrets
import shutil
import tempfile
from pathlib import Path
from typing import Any

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.views import ViewRequest
from services.jobs.isolation import ChildFailed, ChildLimits, exchange_frame
from services.jobs.preflight import checks_folder, public_message, upload_limits
from services.jobs.view_files import VIEW_FILE_PATTERN, OpenView, open_view, view_files, view_json
from services.jobs.view_sessions import ViewSessions
from services.settings import Limits
from services.store.job import JobFiles
from services.uploads.staging import stage_job

__all__ = ["VIEW_FILE_PATTERN", "VIEW_ID_PATTERN", "NoCheckpoint", "OverBudget", "create_view", "view_files"]

#: A view's id: 12 hex digits.
VIEW_ID_PATTERN = r"^[0-9a-f]{12}$"
#: The most bytes of one PNG answered inline (a 256x256 one is about 200 KB).
INLINE_PNG_BYTES = 16 << 20


class NoCheckpoint(Exception):
    """The job has no checkpoint yet (no fields to view)."""


class OverBudget(Exception):
    """The view's files would take the job's files over their disk budget (``job_bytes``)."""


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


def _answer(kind: str, meta: dict) -> dict:
    if kind == "invalid":
        raise InvalidJob(str(meta.get("field", "view")), public_message(str(meta.get("message", "invalid"))))
    if kind != "viewed":
        raise InvalidJob("view", f"the view answered {kind!r}")
    return meta


def _take(written: Path, out: Path) -> None:
    """Move the folder a child wrote a view's files into out of the child's reach (a link is
    moved as a link: :func:`open_view` then refuses it)."""
    try:
        os.rename(written, out)
    except OSError as exc:
        raise InvalidJob("view", f"the view child wrote no folder of files ({exc.strerror})") from None


def render_in_child(spec: JobSpec, checkpoint: bytes, request: ViewRequest, limits: Limits, out: Path) -> dict:
    """Render the view in a sandboxed child, which writes its files into ``out``; returns its
    description. Raises :class:`InvalidJob` (field ``view``, or the scene's) when the view cannot
    be rendered."""
    with tempfile.TemporaryDirectory(prefix="ndrf-view-", dir=checks_folder()) as tmp:
        folder = Path(tmp)
        scene_file = stage_job(spec, folder / "scene", upload_limits(limits))
        (folder / "latest.pt").write_bytes(checkpoint)
        start = {"spec": spec.model_dump(mode="json"), "scene_file": str(scene_file) if scene_file else None,
                 "checkpoint_file": str(folder / "latest.pt"), "request": request.model_dump(mode="json"),
                 "out": str(folder / "out")}
        try:
            kind, meta, _ = exchange_frame("view", start, view_limits(limits), folder, "the view")
        except ChildFailed as exc:
            raise InvalidJob("view", public_message(str(exc))) from None
        meta = _answer(kind, meta)
        _take(folder / "out", out)
    return meta


def render_warm(sessions: ViewSessions, job_id: str, spec: JobSpec, checkpoint: bytes, request: ViewRequest,
                limits: Limits, out: Path, owner: str = "") -> tuple[dict, bool]:
    """The view from this checkpoint's warm child (started if needed), its files in ``out``;
    ``(meta, warm)`` where ``warm`` says an already running child answered. A warm child that
    died (or was closed, idle or evicted, while this request waited for it) is replaced once."""
    for _ in range(2):
        try:
            session, started = sessions.session(job_id, spec, checkpoint, limits, owner)
        except ChildFailed as exc:
            raise InvalidJob("view", public_message(str(exc))) from None
        try:
            kind, meta, _ = session.view(request, out)
        except ChildFailed as exc:
            sessions.drop(session)
            if started and not session.retired:   # retired: closed under it before its view (evicted, replaced)
                raise InvalidJob("view", public_message(str(exc))) from None
            continue
        if (kind == "invalid" and started) or not session.kept:   # no child kept for it
            sessions.drop(session)
        return _answer(kind, meta), not started
    raise InvalidJob("view", "the view child ended twice")


def store_view(files: JobFiles, view_id: str, opened: OpenView, meta: dict, request: ViewRequest,
               limits: Limits) -> dict[str, Any]:
    """The view's files from the child's folder: ``inline``, its PNGs (bytes, by name); else
    copied into the store under ``views/<id>/`` file by file (sizes, by name). Raises
    :class:`OverBudget` before anything is written when they would pass ``job_bytes``."""
    description = view_json({k: v for k, v in meta.items() if k != "scales"}, meta.get("scales", {}))
    if request.inline:
        try:
            return {name: opened.read(name, INLINE_PNG_BYTES) for name in opened.files if name.endswith(".png")}
        except ValueError as exc:
            raise InvalidJob("view", f"an inline image is too large ({exc}): ask without inline") from None
    size, used = opened.total + len(description), files.store.prefix_bytes(files.prefix)
    if used + size > limits.job_bytes:
        raise OverBudget(f"the view's {size} bytes would take the job's files over {limits.job_bytes} bytes "
                         f"(NDRF_MAX_JOB_BYTES; they hold {used}): delete the job's views or ask for a smaller one")
    for name, (handle, length) in opened.files.items():
        files.store.put_file(files.key(f"views/{view_id}/{name}"), handle, length)
    files.store.put(files.key(f"views/{view_id}/view.json"), description)
    return {**{name: length for name, (_, length) in opened.files.items()}, "view.json": len(description)}


def create_view(files: JobFiles, request: ViewRequest, limits: Limits, sessions: ViewSessions | None = None,
                owner: str = "") -> tuple[str, dict[str, Any], dict]:
    """Render a view of the job of ``files`` (the caller has checked who may see it) from its latest
    checkpoint (in a warm child of ``sessions`` when given and enabled, else a one-off child) and,
    unless ``request.inline``, store its files under ``views/<id>/``; returns the id, the files
    (``inline``: the PNGs' bytes by name; else the stored files' sizes by name) and the view's
    description (``warm``: a warm child answered). The child writes the files; they reach the
    store by file, not through this process's memory. Raises :class:`NoCheckpoint`,
    :class:`OverBudget` or :class:`InvalidJob`."""
    stored = files.read(JobFiles.SPEC)
    checkpoint = files.store.get(files.key(JobFiles.CHECKPOINT))
    if stored is None or checkpoint is None:
        raise NoCheckpoint(f"job {files.job_id} has no checkpoint yet: its fields are written with the first one")
    spec = JobSpec.model_validate(stored)
    check_view(request, spec, limits)
    holding = Path(tempfile.mkdtemp(prefix="ndrf-view-out-", dir=checks_folder()))
    try:
        out = holding / "view"
        warm = False
        if sessions is not None and sessions.enabled:
            meta, warm = render_warm(sessions, files.job_id, spec, checkpoint, request, limits, out, owner)
        else:
            meta = render_in_child(spec, checkpoint, request, limits, out)
        meta = {**meta, "request": request.model_dump(mode="json"), "warm": warm}
        try:
            opened = open_view(out)
        except ValueError as exc:
            raise InvalidJob("view", str(exc)) from None
        try:
            view_id = secrets.token_hex(6)
            return view_id, store_view(files, view_id, opened, meta, request, limits), meta
        finally:
            opened.close()
    finally:
        shutil.rmtree(holding, ignore_errors=True)

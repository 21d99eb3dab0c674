"""Checks of a submitted job before it is queued (the API's preflight), so that a bad job is a
4xx naming the field rather than a failed job:

1. the caps on the job file (:func:`services.limits.check_limits`), target image headers;
2. the sandbox of the uploaded files (:mod:`services.uploads`), staged into a throw-away folder;
3. the scene loaded and the job checked by the solver **in a sandboxed child process**
   (:mod:`services.jobs.isolation`): keys exist, targets decode and fit the films;
4. the caps on what the child read from the scene (films, sensors).

The API process itself never imports Mitsuba or torch.
"""

from __future__ import annotations

import logging
import re
import tempfile
from pathlib import Path

from schemas.errors import InvalidJob
from schemas.job import JobSpec, SceneSpec, XmlScene
from services.jobs.isolation import ChildFailed, ChildLimits, exchange
from services.limits import check_limits, check_scene_report, check_target_headers
from services.settings import Limits
from services.uploads.scene import UploadLimits
from services.uploads.staging import stage_job, stage_scene

log = logging.getLogger(__name__)


def upload_limits(limits: Limits) -> UploadLimits:
    return UploadLimits(max_file_bytes=limits.mesh_bytes, max_total_bytes=limits.upload_bytes)


def loader_limits(limits: Limits) -> ChildLimits:
    return ChildLimits(memory_bytes=limits.child_memory_bytes, cpu_seconds=int(limits.preflight_seconds),
                       wall_seconds=limits.preflight_seconds)


#: A native source location in a Mitsuba / Dr.Jit message: ``[parser.cpp:1718] `` or ``(xml.h:12)``.
_SOURCE_LOCATION = re.compile(r"[\[(][\w./-]*\.(?:cpp|cc|c|h|hpp|inl):\d+[\])]\s*")
_TEMP_FOLDER = re.compile(re.escape(tempfile.gettempdir().rstrip("/")) + r"/ndrf-[\w.-]+/(?:scene/)?")
_ABSOLUTE = re.compile(r"(?<![\w.])/(?:[\w.+-]+/)+([\w.+-]+)")


def public_message(text: str) -> str:
    """A scene error as clients see it: the staging folder stripped (``scene.xml``, not
    ``/tmp/ndrf-describe-x/scene/scene.xml``), other absolute paths cut to their last part, and
    native source locations (``[parser.cpp:1718]``) removed. The full text goes to the log."""
    text = _SOURCE_LOCATION.sub("", _TEMP_FOLDER.sub("", text))
    return _ABSOLUTE.sub(r"\1", text)


def _in_child(mode: str, start: dict, scene: SceneSpec, limits: Limits, cwd: Path) -> dict:
    try:
        kind, meta = exchange(mode, start, loader_limits(limits), cwd, "the scene loader")
    except ChildFailed as exc:
        field = "scene.files" if isinstance(scene, XmlScene) and scene.files else "scene"
        log.info("scene loader failed: %s", exc)
        raise InvalidJob(field, f"the scene could not be loaded: {public_message(str(exc))}") from None
    if kind == "invalid":
        message = str(meta.get("message", "invalid"))
        scrubbed = public_message(message)
        if scrubbed != message:
            log.info("scene refused (%s): %s", meta.get("field", "scene"), message)
        raise InvalidJob(str(meta.get("field", "scene")), scrubbed)
    return meta


def checks_folder() -> Path:
    """The folder holding the work folders of scene checks. A sandboxed child hides the folder
    holding its work folder (the other checks'); with the system's temporary folder itself as that
    parent, it would hide everything under it, an installation of the product included."""
    folder = Path(tempfile.gettempdir()) / "ndrf-checks"
    folder.mkdir(mode=0o700, exist_ok=True)
    return folder


def preflight(spec: JobSpec, limits: Limits) -> dict:
    """Every check a job can fail before it runs. Returns what the loader reported (sensors and
    films, scalars); raises :class:`InvalidJob` naming the field."""
    check_limits(spec, limits)
    check_target_headers(spec, limits)
    with tempfile.TemporaryDirectory(prefix="ndrf-preflight-", dir=checks_folder()) as tmp:
        scene_file = stage_job(spec, Path(tmp) / "scene", upload_limits(limits))
        start = {"spec": spec.model_dump(mode="json"), "scene_file": str(scene_file) if scene_file else None,
                 "max_scalars": limits.parameters, "max_texels": limits.texels}
        report = _in_child("check", start, spec.scene, limits, Path(tmp))["report"]
    check_scene_report(spec, report, limits)
    return report


def describe_scene(scene: SceneSpec, limits: Limits) -> dict:
    """The optimizable parameters and the films of a scene (``/v1/scenes/.../parameters``),
    loaded in a sandboxed child like a job's: ``{"parameters": [...], "sensors": [[w, h], ...]}``."""
    with tempfile.TemporaryDirectory(prefix="ndrf-describe-", dir=checks_folder()) as tmp:
        scene_file = stage_scene(scene, Path(tmp) / "scene", upload_limits(limits))
        start = {"scene": scene.model_dump(mode="json"), "scene_file": str(scene_file) if scene_file else None}
        return _in_child("describe", start, scene, limits, Path(tmp))["scene"]

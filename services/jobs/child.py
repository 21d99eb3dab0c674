"""The sandboxed child process (``python -m services.jobs.child MODE LIMITS``), started by
:mod:`services.jobs.isolation`. It reads one start frame on stdin and answers in frames on stdout
(:mod:`services.jobs.frames`); it writes nothing anywhere else.

``check``     load the job's scene and check everything but rendering (the API's preflight):
              answers ``checked`` {report} or ``invalid`` {field, message}
``describe``  load a scene and list its optimizable parameters and films: ``described`` {scene}
``probe``     what the sandbox lets a child do, for the tests and an operator's check: tries to
              create a file in each ``write`` folder, to connect to each ``connect`` address (host
              and port, or a Unix socket's path and 0), to
              list each ``list`` folder, to read each ``read`` file and to unmount each ``unmount``
              folder; answers ``probed`` {write, connect, list, read, unmount, uid, capabilities,
              cwd_writable}
``view``      render a job's fields from a camera (:mod:`services.solver.optimize.field_views`),
              write the view's files into the start's ``out`` folder of its work folder
              (:func:`services.jobs.view_files.write_view`: the arrays never travel through the
              parent) and answer ``viewed`` {scalars, seconds, camera, iteration, method,
              scales}, or ``invalid`` {field, message}
``device``    the device this child runs on (``NDRF_DEVICE`` resolved: :mod:`services.jobs.device`):
              answers ``device`` {device, name, variant, requested, reason}
``run``       run the job (:class:`services.solver.optimize.loop.InverseRenderingRun`), forwarding
           every report as a frame (``plan``, ``targets``, ``progress``, ``iteration``,
           ``checkpoint``) and ending with ``outcome``. SIGUSR1 asks it to cancel, SIGTERM to stop
           and checkpoint (the job goes back to the queue), SIGUSR2 to write the images of its
           next iteration.
"""

from __future__ import annotations

import json
import logging
import signal
import sys
from dataclasses import asdict
from pathlib import Path

from schemas.outcomes import Outcome
from services.jobs.frames import array_bytes, outcome_frame, read_frame, started, write_frame
from services.jobs.isolation import apply_limits

log = logging.getLogger("services.jobs.child")


class PipeReporter:
    """A :class:`~services.solver.optimize.report.RunReporter` that forwards to the parent."""

    def __init__(self, stream):
        self.stream = stream

    def plan(self, plan):
        write_frame(self.stream, "plan", {"plan": plan})

    def targets(self, images):
        write_frame(self.stream, "targets", {}, {str(s): array_bytes(a) for s, a in images.items()})

    def progress(self, kind, payload):
        write_frame(self.stream, "progress", {"kind": kind, "payload": payload})

    def iteration(self, record, renders, gradients, silhouettes=None):
        blobs = {f"render-{s}": array_bytes(a) for s, a in (renders or {}).items()}
        blobs |= {f"gradients-{s}": array_bytes(a) for s, a in (gradients or {}).items()}
        blobs |= {f"silhouette-{s}": array_bytes(a) for s, a in (silhouettes or {}).items()}
        write_frame(self.stream, "iteration", {"record": record.model_dump(mode="json")}, blobs)

    def textures(self, iteration, images):
        write_frame(self.stream, "textures", {"iteration": iteration, "names": sorted(images)},
                    {f"texture-{i}": array_bytes(images[name]) for i, name in enumerate(sorted(images))})

    def meshes(self, iteration, files):
        write_frame(self.stream, "meshes", {"iteration": iteration, "names": sorted(files)},
                    {f"mesh-{i}": files[name] for i, name in enumerate(sorted(files))})

    def checkpoint(self, state, next_iteration):
        write_frame(self.stream, "checkpoint", {"next_iteration": next_iteration}, {"state": state})

    def should_stop(self):
        return STOP[0] if STOP else None

    def images_requested(self):
        asked = bool(IMAGES)
        IMAGES.clear()
        return asked


def _mitsuba_log_to_stderr() -> None:
    """Forward Mitsuba's warnings and the names of the files it loads to stderr, where the parent
    finds the file a crash happened in."""
    from services.solver.backend import use_mitsuba

    mi = use_mitsuba()

    class Appender(mi.Appender):  # type: ignore[name-defined]
        def append(self, level, text):
            if level >= mi.LogLevel.Warn or "Loading" in text:
                sys.stderr.write(text + "\n")
                sys.stderr.flush()

        def log_progress(self, *args):
            pass

    logger = mi.logger()
    logger.clear_appenders()
    logger.add_appender(Appender())
    logger.set_log_level(mi.LogLevel.Debug)


def check(start: dict, out) -> None:
    from schemas.errors import InvalidJob
    from schemas.job import JobSpec
    from services.solver.optimize.setup import check as check_job

    spec = JobSpec.model_validate(start["spec"])
    scene_file = Path(start["scene_file"]) if start.get("scene_file") else None
    try:
        checked = check_job(spec, scene_file, max_scalars=start.get("max_scalars"), max_texels=start.get("max_texels"))
    except InvalidJob as exc:
        write_frame(out, "invalid", {"field": exc.field, "message": exc.message})
        return
    write_frame(out, "checked", {"report": checked.report()})


def describe(start: dict, out) -> None:
    from schemas.errors import InvalidJob
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import differentiable_parameters

    try:
        if start.get("scene_file"):
            scene = load_scene(xml_path=Path(start["scene_file"]))
        else:
            scene = load_scene(builtin=start["scene"]["builtin"])
    except KeyError as exc:
        write_frame(out, "invalid", {"field": "scene.builtin", "message": str(exc.args[0])})
        return
    except (RuntimeError, OSError, ValueError, InvalidJob) as exc:
        write_frame(out, "invalid", {"field": "scene.xml", "message": f"Mitsuba could not load the scene: {exc}"})
        return
    parameters = [{"key": p.key, "size": p.size, "owner": p.owner, "owner_type": p.owner_type, "value": list(p.value),
                   "shape": None if p.shape is None else list(p.shape)} for p in differentiable_parameters(scene.params)]
    sensors = [list(scene.resolution(i)) for i in range(scene.sensor_count)]
    write_frame(out, "described", {"scene": {"parameters": parameters, "sensors": sensors}})


def probe(start: dict, out) -> None:
    import os
    import socket
    import uuid

    from services.jobs.sandbox import capabilities

    def attempt(action) -> str:
        try:
            return f"ok: {action()}"
        except OSError as exc:
            return f"refused: {exc.strerror or exc}"

    def write(folder: str) -> str:
        path = Path(folder) / f"probe-{uuid.uuid4().hex}"
        path.write_text("written by a sandboxed child")
        return str(path)

    def unmount(folder: str) -> str:
        import ctypes

        if ctypes.CDLL("libc.so.6", use_errno=True).umount2(folder.encode(), 2) != 0:  # MNT_DETACH
            errno = ctypes.get_errno()
            raise OSError(errno, os.strerror(errno))
        return f"unmounted {folder}"

    def connect(host: str, port: int) -> str:
        if host.startswith("/"):  # a Unix socket
            with socket.socket(socket.AF_UNIX) as unix:
                unix.connect(host)
                return f"connected to {host}"
        with socket.create_connection((host, port), timeout=2):
            return f"connected to {host}:{port}"

    write_frame(out, "probed", {
        "write": {folder: attempt(lambda f=folder: write(f)) for folder in start.get("write", [])},
        "connect": {f"{h}:{p}": attempt(lambda h=h, p=p: connect(h, int(p))) for h, p in start.get("connect", [])},
        "list": {folder: attempt(lambda f=folder: sorted(os.listdir(f))) for folder in start.get("list", [])},
        "read": {file: attempt(lambda f=file: Path(f).read_text()[:100]) for file in start.get("read", [])},
        "unmount": {folder: attempt(lambda f=folder: unmount(f)) for folder in start.get("unmount", [])},
        "uid": os.getuid(), "capabilities": capabilities(), "cwd_writable": attempt(lambda: write(".")),
        "mounts": {line.split()[4]: line.split()[5] for line in Path("/proc/self/mountinfo").read_text().splitlines()},
    })


def device(start: dict, out) -> None:
    from services.solver.backend import describe_device

    write_frame(out, "device", describe_device())


def run(start: dict, out) -> None:
    from schemas.job import JobSpec
    from services.solver.backend import use_torch
    from services.solver.optimize.loop import InverseRenderingRun

    use_torch()
    spec = JobSpec.model_validate(start["spec"])
    reporter = PipeReporter(out)
    resume = Path(start["resume_file"]).read_bytes() if start.get("resume_file") else None
    scene_file = Path(start["scene_file"]) if start.get("scene_file") else None
    warm = Path(start["warm_file"]).read_bytes() if start.get("warm_file") else None
    outcome = InverseRenderingRun(spec, reporter, scene_file=scene_file, resume=resume, warm=warm).execute()
    write_frame(out, "outcome", *outcome_frame(asdict(outcome)))


def view(start: dict, out) -> None:
    from schemas.errors import InvalidJob
    from schemas.job import JobSpec
    from schemas.views import ViewRequest
    from services.solver.backend import use_torch
    from services.solver.optimize.field_views import render_view, restore

    use_torch()
    spec = JobSpec.model_validate(start["spec"])
    request = ViewRequest.model_validate(start["request"])
    scene_file = Path(start["scene_file"]) if start.get("scene_file") else None
    try:
        restored = restore(spec, Path(start["checkpoint_file"]).read_bytes(), scene_file)
        result = render_view(restored, request)
    except InvalidJob as exc:
        write_frame(out, "invalid", {"field": exc.field, "message": exc.message})
        return
    except ValueError as exc:  # a camera that cannot be built, a checkpoint without fields
        write_frame(out, "invalid", {"field": "view", "message": str(exc)})
        return
    _viewed(out, restored, result, Path(start["out"]))


def _viewed(out, restored, result, folder: Path) -> None:
    """Write a view's files into ``folder`` and answer ``viewed`` (no arrays in the frame)."""
    from services.jobs.view_files import write_view

    written = write_view(folder, result.radiance, result.gradients, result.prb)
    write_frame(out, "viewed", {"scalars": result.scalars, "seconds": result.seconds, "camera": result.camera,
                                "iteration": restored.iteration, "method": restored.method, **written})


def views(start: dict, out) -> None:
    """A warm view child (:mod:`services.jobs.view_sessions`): the checkpoint restored once, then
    one ``viewed`` (or ``invalid``) frame per ``view`` frame {request, out} read, until stdin
    closes; each view's files written into its ``out`` folder as :func:`view` does."""
    from schemas.errors import InvalidJob
    from schemas.job import JobSpec
    from schemas.views import ViewRequest
    from services.solver.backend import use_torch
    from services.solver.optimize.field_views import render_view, restore

    use_torch()
    spec = JobSpec.model_validate(start["spec"])
    scene_file = Path(start["scene_file"]) if start.get("scene_file") else None
    restored, failed = None, None
    try:
        restored = restore(spec, Path(start["checkpoint_file"]).read_bytes(), scene_file)
    except InvalidJob as exc:
        failed = {"field": exc.field, "message": exc.message}
    except ValueError as exc:
        failed = {"field": "view", "message": str(exc)}
    while (frame := read_frame(sys.stdin.buffer)) is not None:
        if failed is not None or restored is None:
            write_frame(out, "invalid", failed)
            continue
        try:
            result = render_view(restored, ViewRequest.model_validate(frame[1]["request"]))
        except InvalidJob as exc:
            write_frame(out, "invalid", {"field": exc.field, "message": exc.message})
            continue
        except ValueError as exc:
            write_frame(out, "invalid", {"field": "view", "message": str(exc)})
            continue
        _viewed(out, restored, result, Path(frame[1]["out"]))


#: The stop the parent asked for (set by the signal handlers, installed first thing in main:
#: before that, SIGUSR1 would kill the child).
STOP: list[str] = []
#: Set by SIGUSR2: the parent relays a request for the next iteration's images.
IMAGES: list[bool] = []


def _ask(reason: str):
    def handler(*_):
        if not STOP:
            STOP.append(reason)
    return handler


def main(argv: list[str]) -> int:
    signal.signal(signal.SIGUSR1, _ask(Outcome.CANCELED))
    signal.signal(signal.SIGTERM, _ask(Outcome.INTERRUPTED))
    signal.signal(signal.SIGUSR2, lambda *_: IMAGES.append(True))
    mode, limits = argv[0], json.loads(argv[1])
    apply_limits(limits)
    logging.basicConfig(level=logging.WARNING, stream=sys.stderr, format="%(levelname)s %(name)s: %(message)s")
    out = sys.stdout.buffer
    sys.stdout = sys.stderr  # nothing but frames on the frame stream
    write_frame(out, "ready")  # the handlers are in place: the parent may signal from now on
    frame = read_frame(sys.stdin.buffer)
    if frame is None or frame[0] != "start":
        log.error("no start frame")
        return 2
    start = started(frame[1], frame[2])   # an uploaded scene's files came as blobs
    if mode == "probe":  # no Mitsuba needed
        probe(start, out)
        return 0
    _mitsuba_log_to_stderr()
    {"check": check, "describe": describe, "view": view, "views": views, "run": run, "device": device}[mode](start, out)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

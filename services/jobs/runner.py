"""One attempt of a job, run in a sandboxed child process and written by its parent.

The parent (a worker, or the API's embedded runner) stages the scene in a local scratch folder,
starts ``python -m services.jobs.child run`` (:mod:`services.jobs.isolation`), and turns the
child's frames into writes of :class:`services.jobs.artifacts.JobWriter` (fenced, budgeted).
Meanwhile it watches:

* the lease (``lost``): the job was taken over, kill the child and write nothing more;
* the host's stop request: ``canceled`` -> SIGUSR1, ``interrupted`` (shutdown) -> SIGTERM; the
  child stops at its next training step, checkpoints (interrupted) and reports its outcome;
* the wall-clock budget (``NDRF_MAX_JOB_SECONDS``) and the disk budget (``NDRF_MAX_JOB_BYTES``).

A child that dies without an outcome (a signal, out of memory) fails the job with a description
("the job's process crashed (SIGSEGV) reading m.ply"); the worker goes on.
"""

from __future__ import annotations

import logging
import queue
import shutil
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.outcomes import Outcome
from schemas.records import IterationRecord, JobStatus
from services.jobs.artifacts import BudgetExceeded, JobWriter
from services.jobs.frames import FrameError, array_from, read_frame, start_frame, write_frame
from services.jobs.isolation import Child, ChildFailed, ChildLimits, kernel_cache, sandboxed
from services.jobs.preflight import upload_limits
from services.jobs.state import Fenced, JobStates
from services.jobs.warm_start import source_checkpoint
from services.settings import Limits
from services.store.base import StoreFull
from services.store.job import JobFiles
from services.uploads.staging import stage_scene

log = logging.getLogger(__name__)

POLL_SECONDS = 0.5
STOP_GRACE_SECONDS = 60.0
#: How the parent asks its child to stop (``services.jobs.child`` installs the handlers).
STOP_SIGNALS = {Outcome.CANCELED: signal.SIGUSR1, Outcome.INTERRUPTED: signal.SIGTERM}


@dataclass
class AttemptResult:
    """How an attempt ended, for the worker: ``succeeded``, ``failed``, ``canceled`` (the job is
    finished), ``interrupted`` (handed back to the queue), or ``fenced`` (another attempt owns it)."""

    outcome: Outcome
    detail: str | None = None


class AttemptRunner:
    def __init__(self, states: JobStates, limits: Limits, scratch: Path):
        self.states, self.limits, self.scratch = states, limits, scratch

    def run(self, job_id: str, attempt: str, *, lost: threading.Event,
            stop: Callable[[], Outcome | None]) -> AttemptResult:
        """Run the attempt ``attempt`` (already claimed in the record) to its end."""
        folder = self.scratch / f"{job_id}-{attempt.rsplit('#', 1)[-1]}"
        try:
            return self._run(job_id, attempt, folder, lost, stop)
        except Fenced as exc:
            log.warning("%s", exc)
            return AttemptResult(Outcome.FENCED, str(exc))
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def _run(self, job_id: str, attempt: str, folder: Path, lost: threading.Event,
             stop: Callable[[], Outcome | None]) -> AttemptResult:
        files = self.states.files(job_id)
        writer = JobWriter(self.states, job_id, attempt=attempt, byte_budget=self.limits.job_bytes)
        writer.guard()  # before staging anything: a stale attempt does nothing at all
        spec = JobSpec.model_validate(files.read(JobFiles.SPEC))
        folder.mkdir(parents=True, exist_ok=True)
        try:
            scene_file = stage_scene(spec.scene, folder / "scene", upload_limits(self.limits))
        except InvalidJob as exc:
            return self._fail(writer, str(exc), exc.field)
        resume = files.resume_checkpoint()
        resume_file = warm_file = None
        if resume is not None:
            resume_file = folder / "resume.pt"
            resume_file.write_bytes(resume)
        elif spec.warm_start is not None:  # the source within this job's tenant only (checked again here)
            try:
                warm = source_checkpoint(self.states, spec, self.states.get(job_id).owner)
            except InvalidJob as exc:
                return self._fail(writer, str(exc), exc.field)
            warm_file = folder / "warm.pt"
            assert warm is not None  # a job with warm_start gets its source's bytes or an InvalidJob
            warm_file.write_bytes(warm)
        kernels = str(kernel_cache(self.scratch, self.states.get(job_id).owner)) if sandboxed() else None
        limits = ChildLimits(memory_bytes=self.limits.child_memory_bytes, wall_seconds=self.limits.job_seconds,
                             kernel_cache=kernels)
        try:
            child = Child("run", limits, folder, label=f"job-{job_id}")
        except ChildFailed as exc:  # NDRF_SANDBOX=required on a machine without namespaces
            return self._fail(writer, str(exc))
        frames: queue.Queue = queue.Queue(maxsize=4)
        reader = threading.Thread(target=_pump, args=(child, frames), name=f"frames-{job_id}", daemon=True)
        try:
            write_frame(child.stdin, "start", *start_frame({"spec": spec.model_dump(mode="json"),
                                                             "scene_file": str(scene_file) if scene_file else None,
                                                             "resume_file": str(resume_file) if resume_file else None,
                                                             "warm_file": str(warm_file) if warm_file else None}))
            child.stdin.close()
        except BrokenPipeError:
            pass
        reader.start()
        try:
            return self._supervise(job_id, child, frames, writer, lost, stop)
        finally:
            child.kill()
            reader.join(5)

    def _supervise(self, job_id: str, child: Child, frames: queue.Queue, writer: JobWriter,
                   lost: threading.Event, stop: Callable[[], Outcome | None]) -> AttemptResult:
        deadline = time.monotonic() + self.limits.job_seconds
        signalled: Outcome | None = None
        stop_deadline = None
        ready = False  # the child signals once its handlers are installed: a signal before would kill it
        images_signalled = False  # SIGUSR2 sent for the record's current images_requested
        while True:
            if lost.is_set():
                raise Fenced(job_id, writer.attempt, "another worker (the lease was lost)")
            if ready and writer.asked_for_images and not images_signalled:
                child.signal(signal.SIGUSR2)  # the next iteration writes its images
                images_signalled = True
            elif not writer.asked_for_images:
                images_signalled = False
            reason = stop()
            if reason and signalled is None and ready:
                signalled, stop_deadline = reason, time.monotonic() + STOP_GRACE_SECONDS
                child.signal(STOP_SIGNALS[reason])
                log.info("job %s: asked the run to stop (%s)", job_id, reason)
            if time.monotonic() > deadline:
                child.kill()
                return self._fail(writer, f"the job exceeded its wall-clock budget of {self.limits.job_seconds:g} s "
                                          f"(NDRF_MAX_JOB_SECONDS)")
            if stop_deadline is not None and time.monotonic() > stop_deadline:
                child.kill()  # it did not stop in time: the last checkpoint stands
                return self._end(writer, {"status": _stopped(signalled), "iterations": _next_iteration(writer.files),
                                          "seconds": 0.0})
            try:
                item = frames.get(timeout=POLL_SECONDS)
            except queue.Empty:
                continue
            if isinstance(item, tuple) and item[0] == "ready":
                ready = True
                continue
            if isinstance(item, BaseException):
                child.kill()
                child.wait()
                if isinstance(item, EOFError) and signalled is not None:
                    # We asked it to stop and it died: our signal arrived before its handler was
                    # installed (the process was starting). Canceled is canceled; a shutdown hands back.
                    return self._end(writer, {"status": _stopped(signalled),
                                              "iterations": _next_iteration(writer.files), "seconds": 0.0})
                if isinstance(item, EOFError):
                    sent = STOP_SIGNALS.get(signalled) if signalled else None
                    if sent is not None and child.proc.returncode == -sent:
                        # it died of our stop signal before its handler was installed (it had just
                        # started): it stopped as asked, and the last checkpoint stands
                        return self._end(writer, {"status": signalled, "iterations": _next_iteration(writer.files),
                                                  "seconds": 0.0})
                    return self._fail(writer, child.describe_exit("the job's process"))
                return self._fail(writer, f"the job's process sent a malformed report ({item})")
            kind, meta, blobs = item
            try:
                if kind == "outcome":
                    return self._end(writer, meta)
                self._dispatch(writer, kind, meta, blobs)
            except BudgetExceeded as exc:
                child.kill()
                return self._fail(writer, str(exc))
            except StoreFull as exc:
                child.kill()
                return self._fail(writer, f"the artifact store is full: {exc}")
            except (FrameError, ValueError) as exc:
                child.kill()
                return self._fail(writer, f"the job's process sent a malformed report ({exc})")

    @staticmethod
    def _dispatch(writer: JobWriter, kind: str, meta: dict, blobs: dict[str, bytes]) -> None:
        if kind == "plan":
            writer.plan(meta["plan"])
        elif kind == "targets":
            writer.targets({int(s): array_from(b, ndim=3) for s, b in blobs.items()})
        elif kind == "progress":
            writer.progress(str(meta["kind"]), dict(meta["payload"]))
        elif kind == "iteration":
            renders = {int(k.split("-", 1)[1]): array_from(b, ndim=3) for k, b in blobs.items()
                       if k.startswith("render-")}
            gradients = {int(k.split("-", 1)[1]): array_from(b, ndim=4) for k, b in blobs.items()
                         if k.startswith("gradients-")}
            writer.iteration(IterationRecord.model_validate(meta["record"]), renders or None, gradients or None)
        elif kind == "textures":
            names = [str(name) for name in meta["names"]]
            iteration = None if meta["iteration"] is None else int(meta["iteration"])
            writer.textures(iteration, {name: array_from(blobs[f"texture-{i}"], ndim=3) for i, name in enumerate(names)})
        elif kind == "checkpoint":
            writer.checkpoint(blobs["state"], int(meta["next_iteration"]))
        else:
            raise FrameError(f"unknown report {kind!r}")

    def _end(self, writer: JobWriter, outcome: dict) -> AttemptResult:
        if outcome.get("status") not in set(Outcome) - {Outcome.FENCED}:
            raise FrameError(f"unknown outcome {outcome.get('status')!r}")
        writer.finish(outcome)
        return AttemptResult(Outcome(outcome["status"]), outcome.get("error"))

    def _fail(self, writer: JobWriter, error: str, field: str | None = None) -> AttemptResult:
        log.warning("job %s failed: %s", writer.job_id, error)
        from services.jobs.preflight import public_message

        error = public_message(error)   # clients read it: no staging folders or native source locations
        try:
            writer.finish({"status": Outcome.FAILED, "iterations": _next_iteration(writer.files), "seconds": 0.0,
                           "error": error, "field": field, "parameters": None})
        except (BudgetExceeded, StoreFull):  # the summary does not fit: the record still says why
            writer.states.transition(writer.job_id, JobStatus.FAILED, fence=writer.attempt, error=error, field=field)
        return AttemptResult(Outcome.FAILED, error)


def _pump(child: Child, frames: queue.Queue) -> None:
    """Read the child's frames into ``frames``; an end of stream is an EOFError item."""
    try:
        while True:
            frame = read_frame(child.stdout)
            if frame is None:
                frames.put(EOFError("the child closed its output"))
                return
            frames.put(frame)
    except (FrameError, OSError, ValueError) as exc:
        frames.put(exc)


def _stopped(signalled: str | None) -> Outcome:
    """How an attempt ends that was asked to stop and stopped (or died) before reporting."""
    return Outcome.INTERRUPTED if signalled == Outcome.INTERRUPTED else Outcome.CANCELED


def _next_iteration(files: JobFiles) -> int:
    done = files.iterations()
    return done[-1] + 1 if done else 0

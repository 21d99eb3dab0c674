"""One attempt of a job, run in a sandboxed child process and written by its parent.

The parent (a worker, or the API's embedded runner) stages the scene in a local scratch folder,
starts ``python -m services.jobs.child run`` (:mod:`services.jobs.isolation`), and turns the
child's frames into writes of :class:`services.jobs.artifacts.JobWriter` (fenced, budgeted).
Meanwhile it watches:

* the lease (``lost``): the job was taken over, kill the child and write nothing more;
* the host's stop request: ``canceled`` -> SIGUSR1, ``interrupted`` (shutdown) -> SIGTERM; the
  child stops at its next training step, checkpoints (interrupted) and reports its outcome. A
  child still in its set-up (no ``plan`` frame yet: nothing to save) gets a short grace only
  (#46: one set-up phase, a big scene's load or its synthetic targets, cannot be interrupted);
* the wall-clock budget (``NDRF_MAX_JOB_SECONDS``) and the disk budget (``NDRF_MAX_JOB_BYTES``).

A child that dies without an outcome (a signal, out of memory) fails the job with a description
("the job's process crashed (SIGSEGV) reading m.ply"); the worker goes on.

An attempt's life is a few named handlers, as in rq's worker (``perform_job``,
``handle_job_success``, ``handle_job_failure``): :meth:`AttemptRunner._perform` stages the files,
starts the child and, in ``finally``, kills it; :meth:`AttemptRunner._supervise` watches it; the
attempt ends in exactly one of ``_handle_outcome`` (the child reported how the run ended),
``_handle_stopped`` (it was asked to stop and ended without a report), ``_handle_failure`` (a
refused job, a crash, a budget, a malformed report), each of which logs it, or :class:`Fenced`
(another attempt owns the job: nothing is written).
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
from services.jobs.frames import FrameError, array_from, outcome_of, read_frame, start_frame, write_frame
from services.jobs.isolation import Child, ChildFailed, ChildLimits, kernel_cache, sandboxed
from services.jobs.preflight import upload_limits
from services.jobs.quotas import attempt_budget
from services.jobs.state import Fenced, JobStates
from services.jobs.warm_start import source_checkpoint
from services.limits import check_limits, check_target_headers
from services.settings import Limits
from services.store.base import StoreFull
from services.store.job import JobFiles
from services.uploads.staging import stage_job

log = logging.getLogger(__name__)

POLL_SECONDS = 0.5
STOP_GRACE_SECONDS = 60.0
#: The grace of a stop asked before the child's ``plan`` frame (#46): in its set-up it has no
#: iterate or checkpoint to save, and one uninterruptible phase may outlast STOP_GRACE_SECONDS.
#: A couple of seconds let a child between phases (its ``_preparing`` polls the stop) or whose
#: ``plan`` frame is already on its way report its own outcome; then it is killed.
SETUP_STOP_GRACE_SECONDS = 2.0
#: How the parent asks its child to stop (``services.jobs.child`` installs the handlers).
STOP_SIGNALS = {Outcome.CANCELED: signal.SIGUSR1, Outcome.INTERRUPTED: signal.SIGTERM}


@dataclass
class AttemptResult:
    """How an attempt ended, for the worker: ``succeeded``, ``failed``, ``canceled`` (the job is
    finished), ``interrupted`` (handed back to the queue), or ``fenced`` (another attempt owns it)."""

    outcome: Outcome
    detail: str | None = None


@dataclass
class _Watch:
    """What the supervision of one attempt knows: the wall-clock ``deadline``, whether the child is
    ``ready`` for signals (its handlers are installed: a signal before would kill it), whether
    it has ``planned`` (sent its ``plan`` frame: its set-up is over), the stop asked of it
    (``stop_sent``, at ``stop_at``) and when its grace ends, and whether the record's current
    images request was passed on."""

    deadline: float
    ready: bool = False
    planned: bool = False
    stop_sent: Outcome | None = None
    stop_at: float | None = None
    images_signalled: bool = False

    @property
    def stop_deadline(self) -> float | None:
        """When the grace of the stop asked ends: :data:`STOP_GRACE_SECONDS` after it once the
        child has planned (a stop asked in the set-up gets the full grace when its plan arrives),
        :data:`SETUP_STOP_GRACE_SECONDS` before."""
        if self.stop_at is None:
            return None
        return self.stop_at + (STOP_GRACE_SECONDS if self.planned else SETUP_STOP_GRACE_SECONDS)


class AttemptRunner:
    def __init__(self, states: JobStates, limits: Limits, scratch: Path):
        self.states, self.limits, self.scratch = states, limits, scratch

    def run(self, job_id: str, attempt: str, *, lost: threading.Event,
            stop: Callable[[], Outcome | None]) -> AttemptResult:
        """Run the attempt ``attempt`` (already claimed in the record) to its end."""
        folder = self.scratch / f"{job_id}-{attempt.rsplit('#', 1)[-1]}"
        try:
            return self._perform(job_id, attempt, folder, lost, stop)
        except Fenced as exc:
            log.warning("%s", exc)
            return AttemptResult(Outcome.FENCED, str(exc))
        finally:
            shutil.rmtree(folder, ignore_errors=True)

    def _perform(self, job_id: str, attempt: str, folder: Path, lost: threading.Event,
                 stop: Callable[[], Outcome | None]) -> AttemptResult:
        """Stage the attempt's files, start its child, supervise it. Whatever ends the attempt, the
        child is killed and its frame reader joined (``finally``)."""
        budget = attempt_budget(self.states, job_id, self.limits)
        writer = JobWriter(self.states, job_id, attempt=attempt, byte_budget=budget.bytes, budget_limit=budget.limit)
        writer.guard()  # before staging anything: a stale attempt does nothing at all
        try:
            start = self._stage(job_id, folder)
            child = Child("run", self._child_limits(job_id), folder, label=f"job-{job_id}")
        except InvalidJob as exc:
            return self._handle_failure(writer, str(exc), exc.field)
        except ChildFailed as exc:  # NDRF_SANDBOX=required on a machine without namespaces
            return self._handle_failure(writer, str(exc))
        frames: queue.Queue = queue.Queue(maxsize=4)
        reader = threading.Thread(target=_pump, args=(child, frames), name=f"frames-{job_id}", daemon=True)
        try:
            reader.start()
            try:
                write_frame(child.stdin, "start", *start_frame(start))
                child.stdin.close()
            except BrokenPipeError:  # it died at once: its end of stream says how
                pass
            return self._supervise(job_id, child, frames, writer, lost, stop)
        finally:
            child.kill()
            reader.join(5)

    def _stage(self, job_id: str, folder: Path) -> dict:
        """The job's scene, and the checkpoint it resumes or warm-starts from, written to
        ``folder``: the child's start frame. A job the checks refuse raises :class:`InvalidJob`."""
        files = self.states.files(job_id)
        spec = JobSpec.model_validate(files.read(JobFiles.SPEC))
        # the caps and the image headers again: an experiment's run whose scene setting was not
        # loaded at creation (NDRF_MAX_EXPERIMENT_CHECKS) is checked here, and fails naming why
        check_limits(spec, self.limits)
        check_target_headers(spec, self.limits)
        folder.mkdir(parents=True, exist_ok=True)
        scene_file = stage_job(spec, folder / "scene", upload_limits(self.limits))
        resume = files.resume_checkpoint()
        resume_file = warm_file = None
        if resume is not None:
            resume_file = folder / "resume.pt"
            resume_file.write_bytes(resume)
        elif spec.warm_start is not None:  # the source within this job's tenant only (checked again here)
            warm = source_checkpoint(self.states, spec, self.states.get(job_id).owner)
            assert warm is not None  # a job with warm_start gets its source's bytes or an InvalidJob
            warm_file = folder / "warm.pt"
            warm_file.write_bytes(warm)
        return {"spec": spec.model_dump(mode="json"), "scene_file": str(scene_file) if scene_file else None,
                "resume_file": str(resume_file) if resume_file else None,
                "warm_file": str(warm_file) if warm_file else None}

    def _child_limits(self, job_id: str) -> ChildLimits:
        """Memory and wall clock of the settings; a sandboxed run's kernel cache is its key's."""
        kernels = str(kernel_cache(self.scratch, self.states.get(job_id).owner)) if sandboxed() else None
        return ChildLimits(memory_bytes=self.limits.child_memory_bytes, wall_seconds=self.limits.job_seconds,
                           kernel_cache=kernels)

    # ------------------------------------------------------------ supervision: a job's life as handlers

    def _supervise(self, job_id: str, child: Child, frames: queue.Queue, writer: JobWriter,
                   lost: threading.Event, stop: Callable[[], Outcome | None]) -> AttemptResult:
        """Watch the child until the attempt ends: the lease, the host's requests, the budgets,
        then the child's next frame. Every way out is one of the ``_handle_*`` methods below (or
        :class:`Fenced`, raised to :meth:`run`); the caller kills the child in ``finally``."""
        watch = _Watch(deadline=time.monotonic() + self.limits.job_seconds)
        while True:
            if lost.is_set():
                raise Fenced(job_id, writer.attempt, "another worker (the lease was lost)")
            self._forward_requests(job_id, child, writer, stop(), watch)
            ended = self._check_clocks(child, writer, watch)
            if ended is not None:
                return ended
            try:
                item = frames.get(timeout=POLL_SECONDS)
            except queue.Empty:
                continue
            ended = self._handle_frame(child, writer, watch, item)
            if ended is not None:
                return ended

    @staticmethod
    def _forward_requests(job_id: str, child: Child, writer: JobWriter, reason: Outcome | None,
                          watch: _Watch) -> None:
        """Pass the record's images request (SIGUSR2, once per request) and the host's stop request
        (``reason``: SIGUSR1 to cancel, SIGTERM to interrupt, once) to a child that is ready for
        signals; starts the grace period of a stop (:data:`SETUP_STOP_GRACE_SECONDS` before the plan)."""
        if not watch.ready:
            return
        if writer.asked_for_images and not watch.images_signalled:
            child.signal(signal.SIGUSR2)  # the next iteration writes its images
        watch.images_signalled = writer.asked_for_images
        if reason and watch.stop_sent is None:
            watch.stop_sent, watch.stop_at = reason, time.monotonic()
            child.signal(STOP_SIGNALS[reason])
            log.info("job %s: asked the run to stop (%s), %s: a grace of %g s", job_id, reason,
                     "running" if watch.planned else "still in its set-up",
                     STOP_GRACE_SECONDS if watch.planned else SETUP_STOP_GRACE_SECONDS)

    def _check_clocks(self, child: Child, writer: JobWriter, watch: _Watch) -> AttemptResult | None:
        """The wall-clock budget (the job fails) and a stop's grace period (it stopped)."""
        now = time.monotonic()
        if now > watch.deadline:
            child.kill()
            return self._handle_failure(writer, f"the job exceeded its wall-clock budget of "
                                                f"{self.limits.job_seconds:g} s (NDRF_MAX_JOB_SECONDS)")
        if watch.stop_sent is not None and watch.stop_deadline is not None and now > watch.stop_deadline:
            child.kill()  # it did not stop in time: the last checkpoint stands
            how = ("did not stop within its grace period" if watch.planned else
                   f"still in its set-up after {SETUP_STOP_GRACE_SECONDS:g} s, killed (nothing to save)")
            return self._handle_stopped(writer, watch.stop_sent, how)
        return None

    def _handle_frame(self, child: Child, writer: JobWriter, watch: _Watch, item) -> AttemptResult | None:
        """One item of the frame reader: the child's readiness, its end of stream (or a frame it got
        wrong), its outcome, or a report to write."""
        if isinstance(item, tuple) and item[0] == "ready":
            watch.ready = True
            return None
        if isinstance(item, BaseException):
            return self._handle_exit(child, writer, watch, item)
        kind, meta, blobs = item
        if kind == "plan":
            self._handle_planned(watch)
        try:
            if kind == "outcome":
                return self._handle_outcome(writer, outcome_of(meta, blobs))
            self._dispatch(writer, kind, meta, blobs)
        except BudgetExceeded as exc:
            child.kill()
            return self._handle_failure(writer, str(exc))
        except StoreFull as exc:
            child.kill()
            return self._handle_failure(writer, f"the artifact store is full: {exc}")
        except (FrameError, ValueError) as exc:
            child.kill()
            return self._handle_failure(writer, f"the job's process sent a malformed report ({exc})")
        return None

    @staticmethod
    def _handle_planned(watch: _Watch) -> None:
        """The set-up is over: a stop from now on, or one already asked in the set-up whose
        short grace is running, gets the full grace (the run saves its answer)."""
        watch.planned = True

    def _handle_exit(self, child: Child, writer: JobWriter, watch: _Watch, item: BaseException) -> AttemptResult:
        """The child's output ended without an outcome (``EOFError``) or could not be read. After a
        stop request the child stopped as asked, however it ended (the last checkpoint stands: a
        canceled job is canceled, an interrupted one handed back); otherwise it crashed."""
        child.kill()
        child.wait()
        if not isinstance(item, EOFError):
            return self._handle_failure(writer, f"the job's process sent a malformed report ({item})")
        if watch.stop_sent is not None:
            return self._handle_stopped(writer, watch.stop_sent, child.describe_exit("its process"))
        return self._handle_failure(writer, child.describe_exit("the job's process"))

    def _handle_outcome(self, writer: JobWriter, outcome: dict) -> AttemptResult:
        """The child reported how the run ended: write it as the job's end."""
        if outcome.get("status") not in set(Outcome) - {Outcome.FENCED}:
            raise FrameError(f"unknown outcome {outcome.get('status')!r}")
        writer.finish(outcome)
        log.info("job %s: the run ended %s", writer.job_id, outcome["status"])
        return AttemptResult(Outcome(outcome["status"]), outcome.get("error"))

    def _handle_stopped(self, writer: JobWriter, asked: Outcome, how: str) -> AttemptResult:
        """A run asked to stop that ended without reporting (``how``): canceled stays canceled, an
        interrupted run goes back to the queue from its last checkpoint."""
        log.info("job %s: the run was asked to stop (%s) and ended without a report: %s", writer.job_id, asked, how)
        return self._handle_outcome(writer, {"status": _stopped(asked), "iterations": _next_iteration(writer.files),
                                             "seconds": 0.0})

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
            silhouettes = {int(k.split("-", 1)[1]): array_from(b, ndim=3) for k, b in blobs.items()
                           if k.startswith("silhouette-")}
            writer.iteration(IterationRecord.model_validate(meta["record"]), renders or None, gradients or None,
                             silhouettes or None)
        elif kind == "textures":
            names = [str(name) for name in meta["names"]]
            iteration = None if meta["iteration"] is None else int(meta["iteration"])
            writer.textures(iteration, {name: array_from(blobs[f"texture-{i}"], ndim=3) for i, name in enumerate(names)})
        elif kind == "meshes":
            names = [str(name) for name in meta["names"]]
            writer.meshes(int(meta["iteration"]), {name: bytes(blobs[f"mesh-{i}"]) for i, name in enumerate(names)})
        elif kind == "checkpoint":
            writer.checkpoint(blobs["state"], int(meta["next_iteration"]))
        else:
            raise FrameError(f"unknown report {kind!r}")

    def _handle_failure(self, writer: JobWriter, error: str, field: str | None = None) -> AttemptResult:
        """The attempt failed (``error``, naming the job field when one is at fault): the job's end."""
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


def _stopped(asked: Outcome) -> Outcome:
    """How an attempt ends that was asked to stop and stopped (or died) before reporting."""
    return Outcome.INTERRUPTED if asked == Outcome.INTERRUPTED else Outcome.CANCELED


def _next_iteration(files: JobFiles) -> int:
    done = files.iterations()
    return done[-1] + 1 if done else 0

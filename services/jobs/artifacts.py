"""The host side of a run's reports: :class:`JobWriter` writes what the loop reports into the
job's files in the artifact store (layout: :mod:`services.store.job`).

Every write of an attempt goes through :meth:`JobWriter._put`, which checks the fence (the job
record still names this attempt) and the job's disk budget first; the record itself only changes
through :class:`services.jobs.state.JobStates`. The same writer serves the worker's parent process
(reports arrive from the sandboxed child) and ``ndrf run`` (reports come from the loop in-process).
"""

from __future__ import annotations

import base64
import logging
import time
from collections.abc import Callable

import numpy as np

from schemas.files import mesh_name
from schemas.outcomes import Outcome
from schemas.records import IterationRecord, JobStatus
from schemas.summary import Summary
from services.jobs.state import Fenced, JobStates
from services.store.files import dumps
from services.store.images import display_png, exr_bytes, gradient_png, npy_bytes, srgb_png
from services.store.job import JobFiles

log = logging.getLogger(__name__)


#: The job record's ``iteration`` is brought up to date at most this often (and at every
#: checkpoint, images request and the end): each update is a read and a compare-and-set write of
#: the record, a third of what writing an iteration costs. Clients follow iterations on the events.
RECORD_SECONDS = 0.5
#: Bytes of the byte budget kept back for what a job writes once its files are refused: the
#: record's last rewrite, the failure's event and the summary.
BUDGET_RESERVE = 32 << 10


class BudgetExceeded(Exception):
    """The job wrote more than its disk budget (``NDRF_MAX_JOB_BYTES``)."""


class JobWriter:
    """Writes one attempt's reports (a :class:`~services.solver.optimize.report.RunReporter`).

    ``attempt``      the attempt id the record must name (None: no fence, as for ``ndrf run``)
    ``byte_budget``  most bytes this job's files may take (None: no budget)
    ``stop``         what :meth:`should_stop` answers (the host's cancel / shutdown check)
    """

    def __init__(self, states: JobStates, job_id: str, *, attempt: str | None = None, byte_budget: int | None = None,
                 stop: Callable[[], str | None] = lambda: None, budget_limit: str = "NDRF_MAX_JOB_BYTES"):
        self.states, self.job_id, self.attempt = states, job_id, attempt
        self.files: JobFiles = states.files(job_id)
        self.byte_budget, self.budget_limit = byte_budget, budget_limit
        self.written = self._existing_bytes() if byte_budget is not None else 0   # what the job's files take
        self._sizes: dict[str, int] = {}   # each key's size as this writer last wrote it
        self._resumed = self.written > 0   # an earlier attempt's keys may be overwritten: their size is asked once
        self.stop = stop
        self.labels: list[str] = []
        self.asked_for_images = False  # the record's images_requested, as the last fence check read it
        self.reported: int | None = None   # the last iteration reported; the record's may lag (RECORD_SECONDS)
        self.recorded_at = float("-inf")

    # ------------------------------------------------------------------ fence

    def guard(self) -> None:
        """Raise :class:`Fenced` unless the record still names this attempt."""
        if self.attempt is not None:
            record = self.states.get(self.job_id)
            self.asked_for_images = record.images_requested
            if record.attempt != self.attempt:
                raise Fenced(self.job_id, self.attempt, record.attempt)

    def _put(self, key: str, data: bytes, *, durable: bool = True) -> None:
        """Store ``data`` under ``key`` within the byte budget. A key written again (the latest
        checkpoint, a resume's images) counts once, at its new size: the budget bounds what the
        job's files take, not what it ever wrote."""
        previous = self._sizes.get(key)
        if previous is None:
            previous = (self.files.store.size(key) or 0) if self._resumed and self.byte_budget is not None else 0
        grown = len(data) - previous
        if self.byte_budget is not None and self.written + grown > self.byte_budget - BUDGET_RESERVE:
            raise BudgetExceeded(f"the job's files would exceed its disk budget of {self.byte_budget >> 20} MiB "
                                 f"({self.budget_limit}); write images less often (images_every)")
        self.files.store.put(key, data, durable=durable)
        self.written += grown
        self._sizes[key] = len(data)

    def _existing_bytes(self) -> int:
        return self.files.store.prefix_bytes(self.files.prefix)

    def event(self, kind: str, *, durable: bool = True, **payload) -> dict:
        """Append an event to the job's log; its line counts against the byte budget (it is never
        refused: the events say what happened, a refusal included)."""
        stored = self.states.event(self.job_id, {"type": kind, "attempt": self.attempt, **payload}, durable=durable)
        if self.byte_budget is not None:
            self.written += len(dumps(stored, indent=None)) + 1
        return stored

    # --------------------------------------------------------------- reports

    def plan(self, plan: dict) -> None:
        self.guard()
        self.labels = list(plan.get("scalars") or [])
        self._put(self.files.key(JobFiles.PLAN), _json(plan))
        self.event("plan", plan=plan)

    def targets(self, images: dict[int, np.ndarray]) -> None:
        """Each sensor's target ``(H, W, 3)`` as ``targets/target-<s>.npy`` (float32), the same
        values as ``.exr`` (OpenEXR, 32-bit float, as the textures) and an sRGB ``.png`` preview."""
        self.guard()
        encoders = {"npy": lambda a: npy_bytes(np.asarray(a, np.float32)), "exr": exr_bytes, "png": srgb_png}
        for sensor, image in sorted(images.items()):
            # Deterministic, written once; durable at the next checkpoint, as the records are (a
            # resume that finds one missing, or a job begun by a version without the .exr, writes
            # it): an fsync each would hold the first iterations' events back behind them
            for ext, encode in encoders.items():
                if not self.files.store.exists(self.files.target_key(sensor, ext)):
                    self._put(self.files.target_key(sensor, ext), encode(image), durable=False)

    def progress(self, kind: str, payload: dict) -> None:
        self.guard()
        self.event(kind, **payload)

    def iteration(self, record: IterationRecord, renders: dict[int, np.ndarray] | None,
                  gradients: dict[int, np.ndarray] | None, silhouettes: dict[int, np.ndarray] | None = None) -> None:
        self.guard()
        k = record.iteration
        for sensor, image in sorted((renders or {}).items()):
            self._put(self.files.iteration_key(k, "render.png" if sensor == 0 else f"render-{sensor}.png"),
                      srgb_png(image))
        for sensor, image in sorted((silhouettes or {}).items()):   # display space already: no tone map
            self._put(self.files.iteration_key(k, "silhouette.png" if sensor == 0 else f"silhouette-{sensor}.png"),
                      display_png(image))
        for sensor, images in sorted((gradients or {}).items()):
            scales = self._gradient_images(k, sensor, images)
            if record.preview_scales is None:  # the first sensor's, as the previews the dashboard shows
                record = record.model_copy(update={"preview_scales": scales})
        # Not fsynced one by one: the next checkpoint flushes them first (ArtifactStore.put)
        self._put(self.files.iteration_key(k), _json(record.model_dump(mode="json")), durable=False)
        self.reported = k
        if record.images or self.asked_for_images or time.monotonic() - self.recorded_at >= RECORD_SECONDS:
            self._record_iteration(images_written=record.images)
        self.event("iteration", durable=False, **record.model_dump(mode="json"))

    def _record_iteration(self, images_written: bool = False) -> None:
        """The job record's ``iteration`` catches up with the last reported one (and a request
        for images is cleared once they are written)."""
        if self.reported is None:
            return
        if images_written:
            after = self.states.transition(self.job_id, fence=self.attempt, iteration=self.reported,
                                           images_requested=False)
        else:
            after = self.states.transition(self.job_id, fence=self.attempt, iteration=self.reported)
        self.asked_for_images = after.images_requested
        self.recorded_at = time.monotonic()

    def _gradient_images(self, k: int, sensor: int, images: np.ndarray) -> list[float]:
        """``gradients.npy`` and one PNG preview per scalar; returns the preview scales."""
        folder = "" if sensor == 0 else f"sensor-{sensor}/"
        self._put(self.files.iteration_key(k, f"{folder}gradients.npy"), npy_bytes(images.astype(np.float32)))
        scales = []
        for i in range(images.shape[0]):
            png, scale = gradient_png(images[i])
            self._put(self.files.iteration_key(k, f"{folder}gradient-{i}.png"), png)
            scales.append(scale)
        return scales

    def textures(self, iteration: int | None, images: dict[str, np.ndarray]) -> None:
        """Each texture as ``<name>.npy`` (``(H, W, C)`` float32), the same values as ``<name>.exr``
        (OpenEXR, 32-bit float) and a PNG preview (a value in sRGB, a ``.dz_dp`` gradient through the
        diverging map): under ``iterations/<k>/textures/``, or ``final/`` at the end (``iteration`` None)."""
        self.guard()
        for name, image in sorted(images.items()):
            key = self.files.texture_key(iteration, name)
            image = np.asarray(image, np.float32)
            self._put(key + ".npy", npy_bytes(image), durable=iteration is None)
            self._put(key + ".exr", exr_bytes(image), durable=iteration is None)
            rgb = np.repeat(image, 3, axis=-1) if image.shape[-1] == 1 else image
            png = gradient_png(rgb)[0] if name.endswith(".dz_dp") else srgb_png(rgb)
            self._put(key + ".png", png, durable=iteration is None)

    def meshes(self, iteration: int, files: dict[str, bytes]) -> None:
        """Each optimized mesh as ``iterations/<k>/meshes/<shape id>.ply``."""
        self.guard()
        for shape, data in sorted(files.items()):
            self._put(self.files.iteration_key(iteration, f"meshes/{mesh_name(shape)}.ply"), data, durable=False)

    def checkpoint(self, state: bytes, next_iteration: int) -> None:
        self.guard()
        self.files.store.flush()   # every record a resume from this checkpoint keeps is durable first
        self._record_iteration()
        # The info first: a resume drops records after the info's iteration and continues from the
        # blob's. Killed between the two writes, an info ahead of the blob only means an iteration is
        # recomputed (same seeds, its record overwritten); an info behind it lost that record.
        self._put(self.files.key(JobFiles.CHECKPOINT_INFO), _json({"next_iteration": next_iteration}))
        self._put(self.files.key(JobFiles.CHECKPOINT), state)
        self.event("checkpoint", iteration=next_iteration)

    def should_stop(self):  # -> StopReason | None, as RunReporter declares
        return self.stop()

    def images_requested(self) -> bool:
        """The record's ``images_requested`` as this attempt last read it (no extra read)."""
        return self.asked_for_images

    # ----------------------------------------------------------------- the end

    def summary(self, outcome) -> Summary:
        """``summary.json`` of a finished run (from a :class:`RunOutcome` or its dict): the
        outcome's answer with the plan's scalars, initial and target values, and the files of
        the recovered textures, poses and meshes."""
        data = outcome if isinstance(outcome, dict) else vars(outcome)
        plan = self.files.read(JobFiles.PLAN, {}) or {}
        fields = {name: data.get(name) for name in ("status", "iterations", "seconds", "estimate", "standard_error",
                                                     "estimate_kind", "estimate_window", "run_error", "floor_error",
                                                     "last_iterate", "stopped", "error", "field", "poses")}
        summary = Summary(**fields, method=plan.get("method"), scalars=plan.get("scalars"), init=plan.get("init"),
                          target_values=plan.get("target_values"))
        textures = [t["key"] for t in plan.get("textures") or []]
        if textures:   # the recovered textures' files (written at the end of a run that got there)
            summary.textures = {key: self._texture_files(key) for key in textures
                                if self.files.store.exists(self.files.texture_key(None, key) + ".npy")}
            for key, files in summary.textures.items():   # a synthetic job's target texture, the error, the last
                for suffix, name in (("target", "target"), ("standard_error", "standard_error"), ("last", "last")):
                    extra = self._texture_files(f"{key}.{suffix}")
                    files.update({name if ext == "npy" else f"{name}_{ext}": path for ext, path in extra.items()
                                  if ext != "png" or suffix != "target"})
        if data.get("poses"):   # a pose job's answer: final/poses.json, as a 4x4 matrix and the XML to paste back
            self._put(self.files.key("final/poses.json"), _json(data["poses"]), durable=True)
        if data.get("meshes"):   # a shape job's answer: final/<shape id>.ply, and its Chamfer distance
            summary.meshes = {}
            for shape, mesh in data["meshes"].items():
                name = f"final/{mesh_name(shape)}.ply"
                self._put(self.files.key(name), base64.b64decode(mesh["ply"]), durable=True)
                summary.meshes[shape] = {**{k: v for k, v in mesh.items() if k != "ply"}, "file": name}
        if summary.estimate and summary.target_values is not None:
            summary.estimate_error = float(np.max(np.abs(np.asarray(summary.estimate)
                                                         - np.asarray(summary.target_values, np.float64))))
        self.guard()
        self._put(self.files.key(JobFiles.SUMMARY), _json(summary.model_dump(mode="json")))
        return summary

    def _texture_files(self, name: str) -> dict[str, str]:
        """``final/<name>.npy|exr|png`` by extension, relative to the job folder: those written (a job
        resumed from an older version's files may lack the ``.exr``)."""
        key = self.files.texture_key(None, name)
        return {ext: key[len(self.files.prefix):] + f".{ext}" for ext in ("npy", "exr", "png")
                if self.files.store.exists(f"{key}.{ext}")}

    def finish(self, outcome) -> JobStatus:
        """Record how the attempt ended: ``interrupted`` hands the job back (queued); anything
        else finishes it. Returns the new status."""
        data = outcome if isinstance(outcome, dict) else vars(outcome)
        self.files.store.flush()
        self._record_iteration()
        if data["status"] == Outcome.INTERRUPTED:
            self.states.transition(self.job_id, JobStatus.QUEUED, fence=self.attempt, expect={JobStatus.RUNNING},
                                   note="interrupted: the worker stopped; resumes from its checkpoint")
            return JobStatus.QUEUED
        self.summary(data)
        status = JobStatus(data["status"])
        self.states.transition(self.job_id, status, fence=self.attempt, expect={JobStatus.RUNNING},
                               error=data.get("error"), field=data.get("field"))
        return status


def _json(value) -> bytes:
    from services.store.files import dumps

    return (dumps(value) + "\n").encode()

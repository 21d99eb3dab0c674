"""The files of one job in the artifact store (the same for the CLI and the service).

    <job>/
      spec.json                     the job as submitted
      plan.json                     what actually runs: resolved settings, scalars, bounds, fields, effects
      record.json                   status, iteration, attempt, error (written only by services.jobs.state)
      events.jsonl                  append-only event log (an object per event in the S3 store)
      targets/target-<s>.npy|.exr|.png  target image of sensor s: float32 (H, W, 3), the same as
                                    OpenEXR (32-bit float), an sRGB preview
      iterations/<k>/record.json    loss, parameters, dz/dp, seconds per phase, residual norms
      iterations/<k>/render.png     candidate of sensor 0 (render-<s>.png for the others)
      iterations/<k>/gradients.npy  dI/dp of sensor 0, float32 (P, H, W, 3), every images_every iterations
      iterations/<k>/gradient-<p>.png
      iterations/<k>/textures/<key>.npy|.png  a texture parameter (H, W, C) and <key>.dz_dp its gradient, with
                                    the images (texture jobs write no gradient-<p>.png)
      final/<key>.npy|.png          a recovered texture parameter, float32 (H, W, C), at the end
      final/poses.json              a pose job's recovered poses: per shape, the 4x4 matrix and the XML
                                    <transform> to paste back
      checkpoints/latest.pt         everything needed to continue (services.solver.optimize.checkpoint)
      checkpoints/latest.json       {"next_iteration": k} of that checkpoint
      summary.json                  final status, parameters, iterations, seconds

``<k>`` is the 0-padded iteration (``000003``); sensor ``s > 0`` writes its gradient images under
``iterations/<k>/sensor-<s>/``.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from services.store.base import ArtifactStore


class JobFiles:
    """Keys and small JSON helpers of the job stored under ``prefix`` (``"<id>/"``)."""

    RECORD, SPEC, PLAN, SUMMARY = "record.json", "spec.json", "plan.json", "summary.json"
    CHECKPOINT, CHECKPOINT_INFO = "checkpoints/latest.pt", "checkpoints/latest.json"

    def __init__(self, store: ArtifactStore, job_id: str):
        self.store = store
        self.job_id = job_id
        self.prefix = f"{job_id}/"

    def __repr__(self) -> str:
        return f"JobFiles({self.store!r}, {self.job_id!r})"

    def key(self, name: str) -> str:
        return self.prefix + name

    def iteration_key(self, k: int, name: str = "record.json") -> str:
        return f"{self.prefix}iterations/{k:06d}/{name}"

    def texture_key(self, k: int | None, name: str) -> str:
        """Key (without extension) of texture ``name`` at iteration ``k``, or recovered (``k`` None)."""
        return f"{self.prefix}final/{name}" if k is None else f"{self.prefix}iterations/{k:06d}/textures/{name}"

    def target_key(self, sensor: int, ext: str) -> str:
        return f"{self.prefix}targets/target-{sensor}.{ext}"

    # ------------------------------------------------------------------ JSON

    def read(self, name: str, default: Any = None) -> Any:
        return self.store.get_json(self.key(name), default)

    def write(self, name: str, value: Any) -> None:
        self.store.put_json(self.key(name), value)

    def exists(self, name: str) -> bool:
        return self.store.exists(self.key(name))

    # ------------------------------------------------------------ iterations

    def iterations(self) -> list[int]:
        """Iteration indices with a complete record, ascending."""
        head = f"{self.prefix}iterations/"
        return sorted(int(key[len(head):].split("/", 1)[0]) for key in self.store.keys(head)
                      if key.endswith("/record.json") and key.count("/") == head.count("/") + 1)

    def iteration_record(self, k: int) -> dict | None:
        return self.store.get_json(self.iteration_key(k))

    def resume_checkpoint(self) -> bytes | None:
        """The checkpoint a resumed attempt continues from (None: start over), with the records it
        will recompute forgotten: those after ``checkpoint.json``'s ``next_iteration``. The info is
        written before the checkpoint (:meth:`services.jobs.artifacts.JobWriter.checkpoint`), so a
        kill between the two leaves it ahead of the checkpoint, never behind: every record the
        checkpoint does not recompute is kept."""
        checkpoint = self.store.get(self.key(self.CHECKPOINT))
        if checkpoint is not None:
            self.drop_iterations_after(int((self.read(self.CHECKPOINT_INFO) or {}).get("next_iteration", 0)) - 1)
        return checkpoint

    def drop_iterations_after(self, k: int) -> None:
        """Forget records newer than iteration ``k`` (a resumed run recomputes them)."""
        for j in self.iterations():
            if j > k:
                self.store.delete_prefix(self.iteration_key(j, ""))

    # ---------------------------------------------------------------- events

    def events(self, after: int = 0) -> Iterator[dict]:
        events, _ = self.store.read_events(self.prefix, after)
        yield from events

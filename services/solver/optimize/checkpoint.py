"""Checkpoints: everything a run needs to continue exactly where it stopped, as bytes (the host
stores them; the solver never touches the store).

A checkpoint holds the index of the next iteration, the parameter vector and its optimizer's state
(Adam's moments; Levenberg-Marquardt's trust radius, its curvature and each view's last two
Jacobians, block-averaged), the position in the stream of views and the batch (views, spp,
gradient spp), the run's events (decisions taken on the way), the answer's iterations
(:mod:`.answer`), both fields and their optimizers (via
``FieldTrainer.state_dict``, which includes the training-step counter that every sample seed
derives from), torch's RNG state, the gradient method that ran, the triangles of a remeshed mesh
(:mod:`.remeshing`), and a fingerprint of the job so
that a checkpoint is never loaded into a different job. It is read with ``weights_only=True``:
tensors and plain data only, so a checkpoint from the store cannot run code.
"""

from __future__ import annotations

import io

import numpy as np
import torch

from schemas.job import JobSpec


def dumps(*, spec: JobSpec, next_iteration: int, parameters: np.ndarray, optimizer: dict, trainer: dict | None,
          views_offset: int = 0, batch: tuple[int, int, int] = (1, 1, 1), events: list[dict] | None = None,
          answer: dict | None = None, attempt: str | None = None, method: str | None = None,
          meshes: dict | None = None) -> bytes:
    state = {
        "fingerprint": spec.fingerprint(),
        "method": method,
        "next_iteration": next_iteration,
        "parameters": np.asarray(parameters, np.float64).tolist(),
        "optimizer": _tensors(optimizer),
        "views_offset": int(views_offset),
        "batch": [int(v) for v in batch],  # views per iteration, spp, gradient spp
        "events": list(events or []),
        "answer": _tensors(answer),
        "trainer": trainer,
        "torch_rng": torch.get_rng_state(),
        "attempt": attempt,
        "meshes": _tensors(meshes),   # remeshed meshes' vertices and faces (:mod:`.remeshing`)
    }
    buffer = io.BytesIO()
    torch.save(state, buffer)
    return buffer.getvalue()


def _tensors(value):
    """``value`` with every numpy array made a tensor (what ``weights_only`` loading accepts)."""
    if isinstance(value, np.ndarray):
        return torch.from_numpy(np.ascontiguousarray(value))
    if isinstance(value, dict):
        return {k: _tensors(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return type(value)(_tensors(v) for v in value)
    return value


def loads(blob: bytes, spec: JobSpec) -> dict:
    """Read a checkpoint; raises ``ValueError`` if it belongs to another job."""
    state = torch.load(io.BytesIO(blob), map_location="cpu", weights_only=True)
    if state.get("fingerprint") != spec.fingerprint():
        raise ValueError("the checkpoint belongs to a different job specification")
    torch.set_rng_state(state["torch_rng"])
    return state

"""Checkpoints: everything a run needs to continue exactly where it stopped.

A checkpoint holds the index of the next iteration, the parameter vector and its Adam state, both
fields and their optimizers (via ``FieldTrainer.state_dict``, which includes the training-step
counter that every sample seed derives from), torch's RNG state, and a fingerprint of the job so
that a checkpoint is never loaded into a different job. Written atomically (temp file + rename).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import torch

from schemas.job import JobSpec
from services.store.files import atomic_write_bytes


def save(path: Path, *, spec: JobSpec, next_iteration: int, parameters: np.ndarray, adam: dict,
         trainer: dict | None, attempt: str | None = None) -> None:
    state = {
        "fingerprint": spec.fingerprint(),
        "next_iteration": next_iteration,
        "parameters": np.asarray(parameters, np.float64).tolist(),
        "adam": adam,
        "trainer": trainer,
        "torch_rng": torch.get_rng_state(),
        "attempt": attempt,
    }
    buffer = io.BytesIO()
    torch.save(state, buffer)
    atomic_write_bytes(path, buffer.getvalue())


def load(path: Path, spec: JobSpec) -> dict:
    """Read a checkpoint; raises ``ValueError`` if it belongs to another job."""
    state = torch.load(path, map_location="cpu", weights_only=True)  # tensors and plain data only
    if state.get("fingerprint") != spec.fingerprint():
        raise ValueError(f"checkpoint {path} belongs to a different job specification")
    torch.set_rng_state(state["torch_rng"])
    return state

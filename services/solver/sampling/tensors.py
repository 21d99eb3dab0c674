"""Dr.Jit lanes <-> torch tensors: the hand-over point between Mitsuba and the neural fields.

Every exchange is zero-copy through DLPack: a flat Dr.Jit array (``mi.Float``, ``mi.Bool``) and the
torch tensor made from it share one buffer, in host memory on the CPU (LLVM) and in GPU memory on
CUDA, so nothing of a lane passes through the host inside an iteration. A ``mi.Color3f`` is three
flat arrays (Dr.Jit keeps one array per channel); its ``(K, 3)`` tensor is stacked from the three
shared views by torch, on the device. ``tests/unit/test_transfers.py`` counts what a training step
and a field query move through the host.

The host is reached only where a value leaves the solver (:func:`to_host`: images, ``dz/dp``) or
enters it (:func:`to_device`: a pixel gradient computed from a target image).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from services.solver.backend import device, torch_device
from services.solver.fields.query import FieldQuery
from services.solver.jit_types import Bool, Color, Float, Vector


def _synchronized() -> None:
    """On CUDA, Dr.Jit's kernels run on its own stream: wait for them before torch reads."""
    if device().kind == "cuda":
        dr.sync_thread()


def flat(value: Float | Bool, width: int | None = None) -> torch.Tensor:
    """``(K,)`` tensor viewing the flat Dr.Jit array ``value`` (no copy); a one-lane literal is
    broadcast to ``width`` lanes (a view too)."""
    value = dr.detach(value)
    dr.eval(value)
    _synchronized()
    t = value.torch()
    return t.expand(width) if width is not None and t.shape[0] == 1 and width != 1 else t


def rgb(value: Color | Vector) -> torch.Tensor:
    """``(K, 3)`` float32 tensor of a ``mi.Color3f`` / ``mi.Vector3f`` with ``K`` lanes (a channel that
    is a one-lane literal is broadcast)."""
    value = dr.detach(value)
    dr.eval(value)                                   # one kernel for the three channels
    width = dr.width(value)
    return torch.stack([flat(value[c], width) for c in range(3)], 1)


def mask(value: Bool) -> torch.Tensor:
    """``(K,)`` bool tensor."""
    return flat(value)


def tensor(value) -> torch.Tensor:
    """The torch tensor viewing a ``mi.TensorXf`` (a developed film: ``(H, W, channels)``; no copy)."""
    value = dr.detach(value)
    dr.eval(value)
    _synchronized()
    return value.torch()


def floats(t: torch.Tensor) -> Float:
    """``mi.Float`` of a ``(K,)`` tensor (DLPack, on the device)."""
    if device().kind == "cuda":
        torch.cuda.synchronize()                     # torch's kernels done before Dr.Jit reads
    return mi.Float(t.detach().to(torch.float32).contiguous())


def color(t: torch.Tensor) -> Color:
    """``mi.Color3f`` of a ``(K, 3)`` tensor (DLPack, on the device)."""
    return mi.Color3f(*(floats(t[:, c]) for c in range(3)))


def to_device(array: np.ndarray, dtype: torch.dtype | None = None) -> torch.Tensor:
    """A host array (a pixel gradient, drawn indices) as a tensor on the solver's device."""
    t = torch.from_numpy(np.ascontiguousarray(array))
    return t.to(device=torch_device(), dtype=dtype or t.dtype)


def to_host(t: torch.Tensor) -> np.ndarray:
    """A tensor leaving the solver (an image, ``dz/dp``) as a numpy array on the host."""
    return t.detach().cpu().numpy()


def field_query(si: mi.SurfaceInteraction3f) -> FieldQuery:
    """The query of every lane of ``si`` (``si.wi`` is the local outgoing direction)."""
    with dr.suspend_grad():
        wo = si.to_world(si.wi)
        n = mi.Vector3f(si.n)
        dr.eval(si.p, wo, n)
    return FieldQuery(rgb(si.p), rgb(wo), rgb(n))

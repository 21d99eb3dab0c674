"""Dr.Jit lanes <-> torch tensors: the hand-over point between Mitsuba and the neural fields.

Every exchange goes through DLPack: a flat Dr.Jit array (``mi.Float``, ``mi.Bool``) and the torch
tensor made from it share one buffer, in host memory on the CPU (LLVM) and in GPU memory on CUDA,
so nothing of a lane passes through the host inside an iteration. A ``mi.Color3f`` is three flat
arrays (Dr.Jit keeps one array per channel); its ``(K, 3)`` tensor is stacked from the three shared
views by torch, on the device. ``tests/unit/test_transfers.py`` counts what a training step and a
field query move through the host.

Lifetimes: what one side hands over stays the other side's only while the call runs. A view of
Dr.Jit's buffer is kept by torch only where it is used at once (stacked, cloned); a tensor handed to
Dr.Jit is copied into Dr.Jit's own buffer by one kernel (:func:`floats`), so that neither library
ever frees the other's memory late, from its garbage collector or in the middle of a recorded
(frozen) function. On CUDA the two libraries run on streams of their own: each exchange waits for
the producer's kernels before the consumer reads, and for the consumer's before the producer may
reuse its buffer (a view is cloned on the device first). None of that reaches the host's memory.

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


def _cuda() -> bool:
    return device().kind == "cuda"


def _view(value) -> torch.Tensor:
    """The torch tensor viewing the buffer of the evaluated Dr.Jit array ``value`` (no copy); on
    CUDA, after Dr.Jit's kernels that write it."""
    value = dr.detach(value)
    dr.eval(value)
    if _cuda():
        dr.sync_thread()
    return value.torch()


def _done(t: torch.Tensor) -> torch.Tensor:
    """``t``, made from views of Dr.Jit's buffers, once torch has finished reading them (on CUDA:
    its stream drained, since Dr.Jit may reuse a buffer as soon as its view is dropped)."""
    if _cuda():
        torch.cuda.current_stream().synchronize()
    return t


def flat(value: Float | Bool, width: int | None = None) -> torch.Tensor:
    """``(K,)`` tensor of the flat Dr.Jit array ``value`` (on the CPU a view of its buffer, on CUDA
    a copy on the device); a one-lane literal is broadcast to ``width`` lanes (a view)."""
    t = _view(value)
    if _cuda():
        t = _done(t.clone())
    return t.expand(width) if width is not None and t.shape[0] == 1 and width != 1 else t


def rgb(value: Color | Vector) -> torch.Tensor:
    """``(K, 3)`` float32 tensor of a ``mi.Color3f`` / ``mi.Vector3f`` with ``K`` lanes (a channel that
    is a one-lane literal is broadcast)."""
    value = dr.detach(value)
    dr.eval(value)                                   # one kernel for the three channels
    width = dr.width(value)
    views = [_view(value[c]) for c in range(3)]
    return _done(torch.stack([v.expand(width) if v.shape[0] == 1 else v for v in views], 1))


def mask(value: Bool) -> torch.Tensor:
    """``(K,)`` bool tensor."""
    return flat(value)


def tensor(value) -> torch.Tensor:
    """The torch tensor of a ``mi.TensorXf`` (a developed film: ``(H, W, channels)``): a view of its
    buffer on the CPU, a copy on the device on CUDA."""
    t = _view(value)
    return _done(t.clone()) if _cuda() else t


def floats(t: torch.Tensor) -> Float:
    """``mi.Float`` of a ``(K,)`` tensor, in a buffer of Dr.Jit's own (one copy kernel on the
    device: Dr.Jit keeps no reference to torch's memory)."""
    if _cuda():
        torch.cuda.current_stream().synchronize()   # torch's kernels done before Dr.Jit reads
    shared = mi.Float(t.detach().to(torch.float32).contiguous())
    own = shared * dr.opaque(mi.Float, 1.0)          # an opaque factor: Dr.Jit cannot fold it away
    dr.eval(own)
    if _cuda():
        dr.sync_thread()                             # read before torch may reuse its buffer
    return own


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

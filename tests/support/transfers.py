"""A counting hook for what passes through host memory between Dr.Jit, torch and numpy.

On the CPU, Dr.Jit's LLVM arrays, numpy arrays and torch tensors all live in host memory, so a copy
through the host cannot be told from a zero-copy exchange by where the data ends up. It can by the
call that made it: each call counted here is, on CUDA, a copy between the GPU and the host (a
memcpy and a synchronisation), whatever the CPU does with it.

``drjit->host``  ``np.array``/``np.asarray`` (``__array__``), ``.numpy()``, ``.item()``, ``bool()`` of a
                 Dr.Jit array (``int()``/``float()`` of a one-lane value go through C slots that
                 cannot be patched: a scalar either way)
``host->torch``  ``torch.from_numpy``, and ``torch.tensor``/``as_tensor``/``asarray`` of a numpy array
``torch->host``  ``.numpy()``, ``.tolist()``, ``.item()``, ``float()``, ``int()``, ``bool()`` of a tensor

A DLPack exchange (``Float.torch()``, ``torch.from_dlpack``, ``mi.Float(tensor)``) is none of these.
Each :class:`Transfer` records its size (elements) and the first line of the solver that made it.
"""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

SOLVER = str(Path(__file__).resolve().parents[2] / "services")


@dataclass(frozen=True)
class Transfer:
    kind: str     # drjit->host, host->torch, torch->host
    call: str     # the counted call
    size: int     # elements moved
    where: str    # file:line of the first frame in services/ (or the caller's)


@dataclass
class Ledger:
    transfers: list[Transfer] = field(default_factory=list)

    def of(self, kind: str) -> list[Transfer]:
        return [t for t in self.transfers if t.kind == kind]

    def larger_than(self, kind: str, size: int) -> list[Transfer]:
        return [t for t in self.of(kind) if t.size > size]

    def __str__(self) -> str:
        return "\n".join(f"  {t.kind:12} {t.call:24} {t.size:>9} at {t.where}" for t in self.transfers) or "  (none)"


def _where() -> str:
    frame = sys._getframe(2)
    first = None
    while frame is not None:
        name = frame.f_code.co_filename
        if first is None and not name.endswith("transfers.py"):
            first = f"{name}:{frame.f_lineno}"
        if name.startswith(SOLVER):
            return f"{Path(name).relative_to(Path(SOLVER).parent)}:{frame.f_lineno}"
        frame = frame.f_back
    return first or "?"


@contextlib.contextmanager
def host_transfers() -> Iterator[Ledger]:
    """Count, inside the block, every call that moves Dr.Jit or torch data through the host."""
    import drjit as dr
    import torch

    ledger = Ledger()
    saved: list[tuple[object, str, object, bool]] = []
    busy = [False]   # a counted call made by another counted call (torch.tensor -> from_numpy) counts once

    def record(kind: str, call: str, size: int) -> None:
        ledger.transfers.append(Transfer(kind, call, int(size), _where()))

    def patch(owner, name: str, kind: str, size_of) -> None:
        original = getattr(owner, name)
        saved.append((owner, name, original, name in vars(owner)))

        def counted(*args, **kwargs):
            if busy[0]:
                return original(*args, **kwargs)
            busy[0] = True
            try:
                result = original(*args, **kwargs)
            finally:
                busy[0] = False
            size = size_of(args, result)
            if size is not None:
                record(kind, f"{getattr(owner, '__name__', owner)}.{name}", size)
            return result

        setattr(owner, name, counted)

    def result_size(args, result):
        return np.size(result)

    def numpy_arg(args, result):
        return int(np.size(args[0])) if args and isinstance(args[0], np.ndarray) else None

    def tensor_size(args, result):
        return args[0].numel()

    for name in ("__array__", "numpy", "to_numpy", "item", "__bool__"):
        patch(dr.ArrayBase, name, "drjit->host", result_size)
    patch(torch, "from_numpy", "host->torch", numpy_arg)
    for name in ("tensor", "as_tensor", "asarray"):
        patch(torch, name, "host->torch", numpy_arg)
    for name in ("numpy", "tolist", "item", "__float__", "__int__", "__bool__"):
        patch(torch.Tensor, name, "torch->host", tensor_size)
    try:
        yield ledger
    finally:
        for owner, name, original, own in reversed(saved):
            if own:
                setattr(owner, name, original)
            else:   # inherited (torch.Tensor's from its C base): remove the patch
                delattr(owner, name)

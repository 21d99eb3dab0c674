"""The one place where the Dr.Jit/Mitsuba backend and the torch thread pool are chosen.

Importing :mod:`mitsuba` or :mod:`drjit` is side-effect free; the LLVM backend is only
initialised when the first LLVM array is created. That lets every module ``import mitsuba as mi``
at the top, while :func:`use_mitsuba` (called by the scene loader, the single entry point to
Mitsuba) sets the variant and the LLVM library lazily.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)

#: The only variant the product runs: CPU (LLVM) with automatic differentiation and RGB colour.
VARIANT = "llvm_ad_rgb"

#: Debian's LLVM 15 aborts in Dr.Jit 1.5 ("Cannot select ... fminimum"); LLVM 19 works.
_LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
)


def _find_llvm() -> str | None:
    for candidate in _LLVM_CANDIDATES:
        if Path(candidate).exists():
            return candidate
    return None


def use_mitsuba():
    """Select the ``llvm_ad_rgb`` variant (once) and return the :mod:`mitsuba` module.

    Raises a clear error when the LLVM library Dr.Jit needs is missing, instead of the
    backend's abort deep inside the first kernel compilation.
    """
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        found = _find_llvm()
        if found is None:
            raise RuntimeError(
                "Dr.Jit needs LLVM 19 on this machine: install Debian's 'libllvm19' "
                "(make install does) or set DRJIT_LIBLLVM_PATH to a libLLVM .so (>= 16)."
            )
        os.environ["DRJIT_LIBLLVM_PATH"] = found
    import mitsuba as mi

    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
        log.debug("mitsuba variant %s, LLVM %s", VARIANT, os.environ["DRJIT_LIBLLVM_PATH"])
    return mi


def use_torch(threads: int | None = None):
    """Return :mod:`torch` with its intra-op thread pool sized to the machine (2 cores here)."""
    import torch

    wanted = threads or int(os.environ.get("NDRF_TORCH_THREADS", "0")) or (os.cpu_count() or 1)
    if torch.get_num_threads() != wanted:
        torch.set_num_threads(wanted)
    return torch

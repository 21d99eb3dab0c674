"""The one place where the device, the Dr.Jit/Mitsuba variant and torch's device are chosen.

``NDRF_DEVICE`` (per process, default ``auto``):

``cpu``     Mitsuba's ``llvm_ad_rgb`` (Dr.Jit's LLVM backend) and torch on the CPU
``cuda``    Mitsuba's ``cuda_ad_rgb`` and torch on the first visible CUDA device; refused with
            :class:`DeviceUnavailable` (naming every reason) where either cannot run
``auto``    ``cuda`` where Mitsuba's ``cuda_ad_rgb`` loads and torch sees a CUDA device, otherwise
            ``cpu``, with the reason logged

The choice is made once per process (:func:`device`), by two probes: Mitsuba's ``cuda_ad_rgb``
loads and runs a kernel; torch sees a CUDA device. :func:`choose` is the pure decision over them
(the unit tests fake both). Which GPU: the first one the process sees; a machine with several
runs one worker per GPU with ``CUDA_VISIBLE_DEVICES`` (docs/guide/deployment.md).

Importing :mod:`mitsuba` or :mod:`drjit` is side-effect free; a backend is only initialised when
the first array is created. That lets every module ``import mitsuba as mi`` at the top, while
:func:`use_mitsuba` (called by the scene loader, the single entry point to Mitsuba) sets the variant
and torch's default device (so every ``torch.zeros``/``torch.tensor``/module parameter of the solver
lands on the chosen device) lazily. Dr.Jit and torch exchange arrays through DLPack
(:mod:`services.solver.sampling.tensors`): on either device the data never passes through the host.
"""

from __future__ import annotations

import functools
import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

log = logging.getLogger(__name__)

#: The environment variable, its values, and the Mitsuba variant of each device.
DEVICE_ENV = "NDRF_DEVICE"
CHOICES = ("auto", "cpu", "cuda")
VARIANTS = {"cpu": "llvm_ad_rgb", "cuda": "cuda_ad_rgb"}

#: Debian's LLVM 15 aborts in Dr.Jit 1.5 ("Cannot select ... fminimum"); LLVM 19 works.
_LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM-19.so",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
)

#: A probe: None where the backend can run, otherwise why it cannot.
Probe = Callable[[], "str | None"]


class DeviceUnavailable(RuntimeError):
    """``NDRF_DEVICE=cuda`` where Mitsuba's CUDA variant or torch's CUDA cannot run."""


@dataclass(frozen=True)
class Device:
    """The device of this process: ``kind`` ``cpu`` or ``cuda``, what was asked, why, and the
    hardware's name."""

    kind: str
    requested: str
    reason: str
    name: str = ""

    @property
    def variant(self) -> str:
        return VARIANTS[self.kind]

    @property
    def torch(self) -> str:
        """torch's name of the device (``cpu`` or ``cuda``: the first visible GPU)."""
        return self.kind

    def to_json(self) -> dict:
        """What ``plan.json``, ``/healthz`` and the bench results record."""
        return {"device": self.kind, "name": self.name, "variant": self.variant, "requested": self.requested,
                "reason": self.reason}


def requested_device(environ: dict[str, str] | None = None) -> str:
    """``NDRF_DEVICE`` of this process (``auto`` when unset); anything else is a loud error."""
    value = (os.environ if environ is None else environ).get(DEVICE_ENV, "auto").strip().lower() or "auto"
    if value not in CHOICES:
        raise ValueError(f"{DEVICE_ENV}={value!r}: expected one of {', '.join(CHOICES)}")
    return value


def choose(requested: str, mitsuba_cuda: Probe, torch_cuda: Probe) -> tuple[str, str]:
    """``(kind, reason)`` for ``requested`` given the two probes (pure: the probes are passed in).

    ``cpu`` probes nothing. ``auto`` probes Mitsuba first and torch only where Mitsuba's CUDA
    runs (on a machine without a GPU torch is then never imported by this choice); ``cuda``
    probes both and raises :class:`DeviceUnavailable` naming every reason it cannot run.
    """
    if requested not in CHOICES:
        raise ValueError(f"{DEVICE_ENV}={requested!r}: expected one of {', '.join(CHOICES)}")
    if requested == "cpu":
        return "cpu", f"{DEVICE_ENV}=cpu"
    reasons = []
    mitsuba_why = mitsuba_cuda()
    if mitsuba_why is not None:
        reasons.append(mitsuba_why)
    if mitsuba_why is None or requested == "cuda":
        torch_why = torch_cuda()
        if torch_why is not None:
            reasons.append(torch_why)
    if not reasons:
        return "cuda", f"{DEVICE_ENV}={requested}: Mitsuba's cuda_ad_rgb runs and torch sees a CUDA device"
    if requested == "cuda":
        raise DeviceUnavailable(f"{DEVICE_ENV}=cuda, but " + "; ".join(reasons)
                                + f" (set {DEVICE_ENV}=cpu or auto to run on the CPU)")
    return "cpu", f"{DEVICE_ENV}=auto: " + "; ".join(reasons)


# ------------------------------------------------------------------ probes (import Mitsuba / torch)

def _find_llvm() -> str | None:
    for candidate in _LLVM_CANDIDATES:
        if Path(candidate).exists():
            return candidate
    return None


def _set_llvm_path() -> None:
    """Point Dr.Jit at LLVM 19 before it is imported (it reads the variable once)."""
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        found = _find_llvm()
        if found is not None:
            os.environ["DRJIT_LIBLLVM_PATH"] = found


def probe_mitsuba_cuda() -> str | None:
    """None where Mitsuba's ``cuda_ad_rgb`` loads and runs a kernel, otherwise why not. Leaves the
    variant at ``cuda_ad_rgb`` when it succeeds."""
    import drjit as dr
    import mitsuba as mi

    if VARIANTS["cuda"] not in mi.variants():
        return f"this Mitsuba {mi.__version__} has no {VARIANTS['cuda']} variant"
    try:
        if not dr.has_backend(dr.JitBackend.CUDA):
            return "Dr.Jit's CUDA backend does not start (no NVIDIA driver or GPU visible to this process)"
        mi.set_variant(VARIANTS["cuda"])
        dr.eval(dr.zeros(mi.Float, 1))
    except Exception as exc:  # whatever the driver or the build says, as the reason
        return f"Mitsuba's {VARIANTS['cuda']} does not load ({type(exc).__name__}: {exc})"
    return None


def probe_torch_cuda() -> str | None:
    """None where torch sees a CUDA device, otherwise why not."""
    import torch

    if torch.version.cuda is None:
        return f"torch {torch.__version__} is a CPU-only build"
    if not torch.cuda.is_available():
        return f"torch {torch.__version__} sees no CUDA device"
    return None


def _cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return f"{line.split(':', 1)[1].strip()} ({os.cpu_count()} cores)"
    except OSError:
        pass
    return f"cpu ({os.cpu_count()} cores)"


@functools.cache
def device() -> Device:
    """The device of this process, chosen once (``NDRF_DEVICE``; see the module docstring)."""
    requested = requested_device()
    _set_llvm_path()
    kind, reason = choose(requested, probe_mitsuba_cuda, probe_torch_cuda)
    if kind == "cuda":
        import torch

        name = torch.cuda.get_device_name(0)
        log.info("device: cuda (%s): %s", name, reason)
    else:
        name = _cpu_name()
        log.info("device: cpu (%s): %s", name, reason)
    return Device(kind, requested, reason, name)


def describe_device() -> dict:
    """The device of this process as plain data (``plan.json``'s ``device``, the bench results)."""
    return device().to_json()


# ------------------------------------------------------------------ selection

def use_mitsuba():
    """Select the device's variant (``llvm_ad_rgb`` or ``cuda_ad_rgb``) and torch's default device
    (once), and return the :mod:`mitsuba` module.

    Raises a clear error when the LLVM library Dr.Jit needs on the CPU is missing, instead of the
    backend's abort deep inside the first kernel compilation.
    """
    chosen = device()
    if chosen.kind == "cpu" and "DRJIT_LIBLLVM_PATH" not in os.environ:
        raise RuntimeError(
            "Dr.Jit needs LLVM 19 on this machine: install Debian's 'libllvm19' "
            "(make install does) or set DRJIT_LIBLLVM_PATH to a libLLVM .so (>= 16).")
    import mitsuba as mi

    if mi.variant() != chosen.variant:
        mi.set_variant(chosen.variant)
        log.debug("mitsuba variant %s (%s)", chosen.variant, chosen.name)
    _torch_default_device(chosen)
    return mi


def _torch_default_device(chosen: Device) -> None:
    """torch's factory functions (``torch.zeros``, ``torch.tensor``, module parameters) create on
    the device from now on; on the CPU nothing changes (torch's own default)."""
    if chosen.kind == "cpu":
        return
    import torch

    if torch.get_default_device().type != chosen.torch:
        torch.set_default_device(chosen.torch)


def torch_device():
    """torch's device of this process (:func:`services.solver.sampling.tensors.to_device` puts host
    arrays there)."""
    import torch

    return torch.device(device().torch)


def use_torch(threads: int | None = None):
    """Return :mod:`torch` with its default device set (:func:`use_mitsuba`) and its intra-op thread
    pool sized to the machine (2 cores here)."""
    import torch

    _torch_default_device(device())
    wanted = threads or int(os.environ.get("NDRF_TORCH_THREADS", "0")) or (os.cpu_count() or 1)
    if torch.get_num_threads() != wanted:
        torch.set_num_threads(wanted)
    return torch

"""Throw-away child processes for everything that parses untrusted scenes with native code.

Mitsuba's loaders are C++; a hostile mesh or document can crash them (or worse). So an uploaded
scene is only ever loaded in a child process started here (``python -m services.jobs.child``):

* resource limits set before it reads anything untrusted: address space, CPU seconds, open files,
  file size, no core dumps; a wall-clock deadline enforced by the parent;
* an environment with nothing secret in it: no API keys, no Redis URL, no cloud credentials
  (the child talks to its parent only, over its stdin/stdout pipes);
* namespaces of its own where the machine allows (:mod:`services.jobs.sandbox`): no network (no
  route to Redis), a read-only filesystem but its work folder, the store hidden, no capabilities;
  where it does not, an ERROR in the log says so and the points here are what holds;
* its own process group, and ``PR_SET_PDEATHSIG``: it dies with the parent, and the parent kills
  it with everything it started;
* its parent's priority: a new session is a new scheduler autogroup on Linux, which would
  otherwise give the child a full share next to an API on the same cores, whatever ``nice`` the
  worker was started with (:func:`keep_priority`);
* its stderr is kept (the tail names the file Mitsuba was loading when it crashed).

A child that dies by a signal, runs out of memory or time is described by :func:`describe_exit`
("the loader crashed (SIGSEGV) reading m.ply"), never a dead API or worker.
"""

from __future__ import annotations

import contextlib
import ctypes
import json
import logging
import os
import re
import resource
import shutil
import signal
import subprocess
import sys
import threading
from collections import deque
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import BinaryIO

from services.jobs import sandbox

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]

#: Variables a child may inherit (nothing secret: no keys, no URLs, no credentials), the GPU's too:
#: which devices it sees and where the driver's libraries are. NDRF_DEVICE is the Settings' value.
_KEEP = ("PATH", "LANG", "LC_ALL", "HOME", "TMPDIR", "DRJIT_LIBLLVM_PATH", "NDRF_TORCH_THREADS", "PYTHONHASHSEED",
         "DRJIT_CACHE_DIR", "CUDA_VISIBLE_DEVICES", "LD_LIBRARY_PATH", "DRJIT_LIBCUDA_PATH")
#: Present where an NVIDIA driver is loaded.
NVIDIA_DEVICE = Path("/dev/nvidiactl")
_LOADING = re.compile(r'Loading (?:mesh|XML file|texture|bitmap|spectrum)?\s*(?:from )?"([^"]+)"', re.IGNORECASE)


@dataclass(frozen=True)
class ChildLimits:
    """Resource limits of one child (``NDRF_CHILD_*`` / ``NDRF_MAX_JOB_SECONDS`` settings)."""

    memory_bytes: int = 8 << 30
    cpu_seconds: int | None = None
    wall_seconds: float | None = None
    open_files: int = 512
    file_bytes: int = 2 << 30
    #: Folders covered by an empty read-only tmpfs in the child, besides the store folder of the
    #: settings and the folder holding the child's work folder (:func:`hidden`).
    hide: tuple[str, ...] = ()
    #: A writable folder for the child's Dr.Jit kernel cache, shared by the jobs of one API key
    #: only (None: the shared cache, read-only, with a private overlay).
    kernel_cache: str | None = None


def hidden(limits: ChildLimits, cwd: Path) -> list[str]:
    """What a sandboxed child must not see: the store folder (``NDRF_STORE``, when a folder), the
    folder holding its work folder (the other jobs' scratch folders, the other uploads being
    checked), ``NDRF_SANDBOX_HIDE`` and ``limits.hide``."""
    from services.settings import get_settings

    settings = get_settings()
    store = settings.store
    folders = [str(cwd.resolve().parent), *settings.sandbox_hide, *limits.hide]
    if "://" not in store:
        folders.append(str(Path(store).resolve()))
    return folders


#: The shared kernel cache is copied into a key's new cache folder up to this size (larger: the
#: key's jobs compile their kernels once themselves).
SEED_BYTES = 256 << 20


#: The folder of the scratch folder that holds the keys' kernel caches (kept across attempts).
KERNELS = "kernels"


def kernel_cache(scratch: Path, owner: str) -> Path:
    """The Dr.Jit kernel cache folder of one API key's sandboxed runs (created on first use as a
    *copy* of the shared cache, so that a key starts warm and what its children add or alter
    never reaches the shared cache, nor any other key's children)."""
    folder = scratch / KERNELS / re.sub(r"[^0-9A-Za-z_-]", "_", owner)
    if folder.is_dir():
        return folder
    shared = Path(os.environ.get("DRJIT_CACHE_DIR") or Path.home() / ".drjit")
    staging = folder.with_name(f".{folder.name}-{os.getpid()}-{threading.get_ident()}")
    staging.mkdir(parents=True, exist_ok=True)
    try:
        files = [f for f in shared.iterdir() if f.is_file()] if shared.is_dir() else []
        if sum(f.stat().st_size for f in files) <= SEED_BYTES:
            for file in files:
                shutil.copyfile(file, staging / file.name)
        staging.rename(folder)
    except OSError as exc:  # another worker made it meanwhile, or the copy failed: an empty cache
        log.debug("kernel cache of %s: %s", owner, exc)
        shutil.rmtree(staging, ignore_errors=True)
        folder.mkdir(parents=True, exist_ok=True)
    return folder


def sandboxed() -> bool:
    """Whether children start in namespaces here (``NDRF_SANDBOX`` and what the machine allows)."""
    from services.settings import get_settings

    try:
        return bool(sandbox.command_prefix(get_settings().sandbox))
    except sandbox.SandboxUnavailable:
        return False


def sandbox_state() -> str:
    """How children start here, for the start-up log line of a worker (``NDRF_SANDBOX=required``
    on a machine without namespaces raises :class:`services.jobs.sandbox.SandboxUnavailable`)."""
    from services.settings import get_settings

    prefix = sandbox.command_prefix(get_settings().sandbox)
    return "namespaces (" + " ".join(prefix[1:-1]) + ")" if prefix else "NONE (see the error above)"


def _command(mode: str, limits: ChildLimits, cwd: Path) -> list[str]:
    """The child's command line: through ``unshare`` when the sandbox is on (``NDRF_SANDBOX``)."""
    from services.settings import get_settings

    prefix = sandbox.command_prefix(get_settings().sandbox)
    spec = {**asdict(limits), "sandbox": {"namespaces": bool(prefix), "hide": hidden(limits, cwd),
                                          "parent_ns": sandbox.namespaces(), "kernel_cache": limits.kernel_cache}}
    return [*prefix, sys.executable, "-m", "services.jobs.child", mode, json.dumps(spec)]


def _environment() -> dict[str, str]:
    from services.settings import get_settings

    env = {k: v for k, v in os.environ.items() if k in _KEEP}
    env["NDRF_DEVICE"] = get_settings().device
    # the child imports this checkout's code, whatever the cwd, then what the parent's path adds
    # (packages unpacked beside the interpreter's, as bench/gpu_check.sh does on a lent GPU)
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), *(p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep)
                                                       if p and Path(p).resolve() != ROOT)])
    env.setdefault("PYTHONHASHSEED", "0")
    return env


def apply_limits(limits: dict) -> None:
    """Called first thing in the child (before it imports Mitsuba or reads anything untrusted):
    die with the parent, then the resource limits. Done in the child rather than in a
    ``preexec_fn``, which is unsafe in a multi-threaded parent such as the API."""
    try:
        libc = ctypes.CDLL("libc.so.6", use_errno=True)
        libc.prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass
    if os.getppid() == 1:  # the parent died before PDEATHSIG was set
        os._exit(1)
    keep_priority()
    resource.setrlimit(memory_limit(), (limits["memory_bytes"], limits["memory_bytes"]))
    resource.setrlimit(resource.RLIMIT_NOFILE, (limits["open_files"], limits["open_files"]))
    resource.setrlimit(resource.RLIMIT_FSIZE, (limits["file_bytes"], limits["file_bytes"]))
    resource.setrlimit(resource.RLIMIT_CORE, (0, 0))
    if limits.get("cpu_seconds") is not None:
        resource.setrlimit(resource.RLIMIT_CPU, (limits["cpu_seconds"], limits["cpu_seconds"] + 5))
    sandbox.enter(limits.get("sandbox", {}))


def memory_limit(device: str | None = None, nvidia: bool | None = None) -> int:
    """The rlimit that holds a child's memory: its address space (``RLIMIT_AS``), except where the
    child may start CUDA (``NDRF_DEVICE`` not ``cpu`` on a machine with an NVIDIA driver). There
    the driver reserves far more address space than the limit at its start, whatever memory it then
    uses, and CUDA would not start: the limit is on the data segment instead (``RLIMIT_DATA``: the
    heap and private writable mappings, which the reservation and GPU memory are not)."""
    device = (os.environ.get("NDRF_DEVICE", "auto") if device is None else device).strip().lower()
    nvidia = NVIDIA_DEVICE.exists() if nvidia is None else nvidia
    return resource.RLIMIT_DATA if nvidia and device != "cpu" else resource.RLIMIT_AS


def keep_priority() -> None:
    """Give the session this process leads (a child started with ``start_new_session``) the
    niceness of this process, which it inherited from its parent.

    With ``kernel.sched_autogroup_enabled`` (the default on most distributions) CPU time is shared
    fairly between *sessions* first, and ``nice`` only orders processes inside one. A worker run
    with ``nice -n 19`` so that it soaks up idle CPU next to an API would start its jobs in new
    sessions at the autogroup's default nice 0: each one as loud as the API. Raising an autogroup's
    nice needs no privilege; where there is no autogroup (or no ``/proc``) this does nothing.
    """
    nice = os.getpriority(os.PRIO_PROCESS, 0)
    if nice > 0:
        with contextlib.suppress(OSError):
            Path("/proc/self/autogroup").write_text(f"{nice}\n")


class Child:
    """A running child: its pipes, the tail of its stderr, and how it ended."""

    stdin: BinaryIO
    stdout: BinaryIO

    def __init__(self, mode: str, limits: ChildLimits, cwd: Path, label: str):
        self.limits, self.label = limits, label
        try:
            command = _command(mode, limits, cwd)
        except sandbox.SandboxUnavailable as exc:
            raise ChildFailed(str(exc)) from None
        self.proc: subprocess.Popen[bytes] = subprocess.Popen(
            command, cwd=cwd,
            env=_environment(), stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
            start_new_session=True, close_fds=True)
        self.stdin, self.stdout = self.proc.stdin, self.proc.stdout  # type: ignore[assignment]
        self.stderr_tail: deque[str] = deque(maxlen=200)
        self.last_file: str | None = None
        self._drain = threading.Thread(target=self._read_stderr, name=f"stderr-{label}", daemon=True)
        self._drain.start()

    def _read_stderr(self) -> None:
        assert self.proc.stderr is not None
        for raw in self.proc.stderr:
            line = raw.decode("utf-8", "replace").rstrip()
            self.stderr_tail.append(line)
            match = _LOADING.search(line)
            if match:
                self.last_file = match.group(1)
            log.debug("[%s] %s", self.label, line)

    def kill(self) -> None:
        """Kill the child's whole process group (it may have started threads or processes)."""
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
        self.proc.wait()

    def signal(self, sig: int) -> None:
        if self.proc.poll() is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.send_signal(sig)

    def wait(self, timeout: float | None = None) -> int:
        code = self.proc.wait(timeout)
        self._drain.join(timeout=5)
        return code

    def describe_exit(self, what: str = "the loader", timed_out: bool = False) -> str:
        """Why the child ended without answering, for a user."""
        code = self.proc.returncode
        reading = f" reading {Path(self.last_file).name}" if self.last_file else ""
        if timed_out:
            return f"{what} took longer than {self.limits.wall_seconds:g} s{reading} and was stopped"
        if code is not None and code < 0:
            sig = signal.Signals(-code)
            if sig == signal.SIGXCPU:
                return f"{what} used more than {self.limits.cpu_seconds} CPU seconds{reading} and was stopped"
            return f"{what} crashed ({sig.name}){reading}"
        memory = any("MemoryError" in line or "bad_alloc" in line or "Cannot allocate memory" in line
                     for line in self.stderr_tail)
        if memory:
            return f"{what} ran out of memory (limit {self.limits.memory_bytes >> 20} MiB){reading}"
        last = next((line for line in reversed(self.stderr_tail) if line.strip()), "")
        return f"{what} exited with status {code}{reading}" + (f": {last[-300:]}" if last else "")


def exchange(mode: str, start: dict, limits: ChildLimits, cwd: Path, what: str) -> tuple[str, dict]:
    """Start a child, send it ``start``, and wait (at most ``limits.wall_seconds``) for its one
    answer frame: ``(kind, meta)``. A child that dies or times out raises :class:`ChildFailed`
    with a description for the user."""
    kind, meta, _ = exchange_frame(mode, start, limits, cwd, what)
    return kind, meta


def exchange_frame(mode: str, start: dict, limits: ChildLimits, cwd: Path,
                   what: str) -> tuple[str, dict, dict[str, bytes]]:
    """:func:`exchange`, with the answer's blobs."""
    from services.jobs.frames import FrameError, read_frame, start_frame, write_frame

    child = Child(mode, limits, cwd, label=f"{mode}-{os.getpid()}")
    answer: list = []

    def read() -> None:
        try:
            frame = read_frame(child.stdout)
            while frame is not None and frame[0] == "ready":
                frame = read_frame(child.stdout)
            answer.append(frame)
        except (FrameError, OSError) as exc:
            answer.append(exc)

    reader = threading.Thread(target=read, name=f"{mode}-answer", daemon=True)
    try:
        try:
            write_frame(child.stdin, "start", *start_frame(start))
            child.stdin.close()
        except BrokenPipeError:
            pass  # it died at once: described below
        reader.start()
        reader.join(limits.wall_seconds)
        timed_out = reader.is_alive()
        if timed_out:
            child.kill()
            reader.join(5)
            raise ChildFailed(child.describe_exit(what, timed_out=True))
        child.wait(timeout=limits.wall_seconds)
        frame = answer[0] if answer else None
        if not isinstance(frame, tuple):
            raise ChildFailed(child.describe_exit(what))
        return frame[0], frame[1], frame[2]
    finally:
        child.kill()


class ChildFailed(RuntimeError):
    """A sandboxed child ended without an answer (crash, signal, out of memory or time)."""

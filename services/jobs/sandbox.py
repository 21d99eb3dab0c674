"""The namespaces a sandboxed child runs in: no network, a read-only filesystem, no privileges.

Guards the store and Redis against a child that a hostile scene took over (a Mitsuba parser bug):
the parent writes the store, the child only computes and talks to its parent over its pipes, so
the child needs neither. Set up in two halves:

* parent (:func:`command_prefix`): the child is started through ``unshare`` (util-linux) in new
  network, mount and IPC namespaces (plus a user namespace, mapping the service's uid to root
  inside, when the service does not run as root: creating the others needs it then). The new
  network namespace has only a loopback interface, down: no route to Redis, to S3, to anything.
* child (:func:`enter`, before it reads anything untrusted): every mount is remounted read-only;
  the store folder, the folder holding the child's work folder (other jobs' scratch folders,
  other uploads being checked) and ``/run`` (Unix sockets: Redis's, Docker's) are covered by
  empty read-only tmpfs; the work folder alone is bound back, writable; ``/dev/shm`` is a private
  tmpfs; Dr.Jit's kernel cache is the folder of the job's API key (a run: the key's jobs reuse
  their kernels), or an overlay on the shared cache whose writes land in ``/dev/shm`` (a scene
  check): a child cannot plant code that another key's child would run. Then it drops every
  capability and sets ``no_new_privs``: it cannot undo a mount, nor gain privileges by running a
  set-uid program.

``NDRF_SANDBOX`` (:class:`services.settings.Settings`) chooses: ``auto`` (the default) uses the
namespaces where ``unshare`` works and otherwise runs children *without* them, logging an
ERROR once per process that says so; ``required`` refuses to start a child without them; ``off``
never uses them. Without the namespaces only the rest of :mod:`services.jobs.isolation` holds
(limits, stripped environment, own process group): such a child can write wherever the service's
uid can, the store included, and connect to Redis. ``docs/security.md`` states both states.
"""

from __future__ import annotations

import ctypes
import functools
import logging
import os
import shutil
import subprocess
import sys
from pathlib import Path

log = logging.getLogger(__name__)

#: ``unshare`` options: the service's uid is root (it may create namespaces) or not (a user
#: namespace first, which makes it root inside, over these namespaces only).
ROOT_FLAGS = ("--net", "--mount", "--ipc", "--propagation", "private")
USER_FLAGS = ("--user", "--map-root-user", *ROOT_FLAGS)
#: Always hidden: where Unix sockets live (Redis's, Docker's, D-Bus's). A read-only mount does not
#: stop a connect() to a socket file, and a network namespace only cuts the abstract ones.
SOCKET_FOLDERS = ("/run", "/var/run")
SHM_BYTES = 256 << 20  # the private /dev/shm (with the child's additions to the kernel cache)

MS_RDONLY, MS_NOSUID, MS_NODEV, MS_NOEXEC, MS_REMOUNT, MS_BIND, MS_REC = 1, 2, 4, 8, 32, 4096, 16384
#: statvfs flags that a bind remount must repeat (those of the mount, locked in a user namespace).
_KEPT = MS_NOSUID | MS_NODEV | MS_NOEXEC | 16 | 64 | 1024 | 2048 | 4096
#: Pseudo filesystems whose mounts may refuse a read-only remount (what they expose is guarded
#: by the dropped capabilities, not by the mount flag).
_PSEUDO = ("/proc", "/sys", "/dev")
#: ``/proc`` itself stays writable: NVIDIA's user-mode driver writes there as CUDA starts, and under
#: a read-only ``/proc`` neither torch nor Dr.Jit find the GPU (measured on a lent H100, issue 35:
#: bench/investigations/README.md). What a root child could change through it is made read-only
#: instead, as container runtimes do: the kernel's settings, the SysRq trigger, IRQ and bus tuning.
PROC_READ_ONLY = ("/proc/sys", "/proc/sysrq-trigger", "/proc/irq", "/proc/bus", "/proc/fs")
PR_SET_NO_NEW_PRIVS, PR_CAPBSET_DROP, PR_CAP_AMBIENT, PR_CAP_AMBIENT_CLEAR_ALL = 38, 24, 47, 4


class SandboxUnavailable(RuntimeError):
    """``NDRF_SANDBOX=required`` and the namespaces cannot be created here."""


@functools.lru_cache(maxsize=1)
def probe() -> tuple[tuple[str, ...] | None, str]:
    """The ``unshare`` command that works on this machine (None if none), and why."""
    binary = shutil.which("unshare")
    if binary is None:
        return None, "util-linux unshare is not installed"
    flags = ROOT_FLAGS if os.geteuid() == 0 else USER_FLAGS
    try:
        done = subprocess.run([binary, *flags, "true"], capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return None, f"unshare failed: {exc}"
    if done.returncode != 0:
        return None, f"unshare {' '.join(flags)} failed: {done.stderr.strip()[-300:]}"
    return (binary, *flags, "--"), "unshare " + " ".join(flags)


@functools.lru_cache(maxsize=4)
def command_prefix(policy: str) -> tuple[str, ...]:
    """What the child's command starts with under ``policy`` (empty: no namespaces), logged once."""
    if policy == "off":
        log.error("CHILD SANDBOX OFF (NDRF_SANDBOX=off): children can write wherever this process can "
                  "(the store included) and reach the network (Redis)")
        return ()
    command, how = probe()
    if command is None:
        if policy == "required":
            raise SandboxUnavailable(f"NDRF_SANDBOX=required but the child's namespaces cannot be created: {how}")
        log.error("CHILD SANDBOX UNAVAILABLE (%s): children run WITHOUT namespaces: they can write wherever this "
                  "process can (the store included) and reach the network (Redis). Only resource limits, a "
                  "stripped environment and their own process group hold. See docs/security.md.", how)
        return ()
    log.info("child sandbox: %s (no network, read-only filesystem but the work folder, no capabilities)", how)
    return command


# ------------------------------------------------------------------------------------ in the child

def _libc() -> ctypes.CDLL:
    return ctypes.CDLL("libc.so.6", use_errno=True)


def _mount(libc: ctypes.CDLL, source: str | None, target: str, fstype: str | None, flags: int,
           data: str | None = None) -> None:
    enc = (lambda s: s.encode() if s is not None else None)
    if libc.mount(enc(source), enc(target), enc(fstype), ctypes.c_ulong(flags), enc(data)) != 0:
        errno = ctypes.get_errno()
        raise OSError(errno, f"mount {target}: {os.strerror(errno)}")


def _mount_points() -> list[str]:
    points = []
    with open("/proc/self/mountinfo") as info:
        for line in info:
            point = line.split()[4]
            points.append(point.encode().decode("unicode_escape"))  # octal escapes (\040: a space)
    return points


def _read_only(libc: ctypes.CDLL, point: str) -> None:
    flags = os.statvfs(point).f_flag & _KEPT
    _mount(libc, None, point, None, MS_REMOUNT | MS_BIND | MS_RDONLY | flags)


def _inside(path: Path, folder: Path) -> bool:
    return path == folder or folder in path.parents


def enter(spec: dict) -> None:
    """Called first thing in the child (after the resource limits, before anything untrusted is
    read), when the parent started it in namespaces (``spec["namespaces"]``). Any failure raises:
    the child then dies before it reads the scene, rather than run with half a sandbox."""
    if not spec.get("namespaces"):
        return
    _check_namespaces(spec.get("parent_ns", {}))
    libc = _libc()
    work = Path.cwd().resolve()
    for point in _mount_points():                              # 1. every mount read-only, but /proc
        if point == "/proc":
            continue
        try:
            _read_only(libc, point)
        except FileNotFoundError:  # under a mount that covers it: not reachable by any path
            continue
        except OSError:
            if not point.startswith(_PSEUDO):
                raise
    _proc_read_only(libc)
    # 2. a private /dev/shm, also holding the writes of the kernel cache's overlay
    _mount(libc, "tmpfs", "/dev/shm", "tmpfs", MS_NOSUID | MS_NODEV, f"size={SHM_BYTES},mode=1777")
    folders = sorted({Path(p).resolve() for p in (*spec.get("hide", []), *SOCKET_FOLDERS) if Path(p).is_dir()},
                     key=lambda p: len(p.parts))
    hidden: list[Path] = []
    for folder in folders:                                     # the outermost (the others are inside)
        if not any(_inside(folder, outer) for outer in hidden):
            hidden.append(folder)
    _refuse_to_hide_the_code(hidden)
    _kernel_cache(libc, hidden, spec.get("kernel_cache"))
    for file in {Path(p).resolve() for p in spec.get("hide", []) if Path(p).exists() and not Path(p).is_dir()}:
        _mount(libc, "/dev/null", str(file), None, MS_BIND)    # a file reads empty, a socket refuses
        _read_only(libc, str(file))
    for folder in hidden:                                      # 3. cover the store and the scratch root
        _mount(libc, "tmpfs", str(folder), "tmpfs", MS_NOSUID | MS_NODEV | MS_NOEXEC, "size=64k,mode=755")
        if _inside(work, folder):
            (folder / work.relative_to(folder)).mkdir(parents=True, exist_ok=True)
        _mount(libc, None, str(folder), None, MS_REMOUNT | MS_RDONLY | MS_NOSUID | MS_NODEV | MS_NOEXEC)
    # 4. the work folder, bound back writable (from the process's own reference to it)
    _mount(libc, "/proc/self/cwd", str(work), None, MS_BIND | MS_REC)  # with what is mounted inside
    kept = os.statvfs(work).f_flag & _KEPT                     # a user namespace locks them
    _mount(libc, None, str(work), None, MS_REMOUNT | MS_BIND | MS_NOSUID | MS_NODEV | kept)
    os.chdir(work)                                             # onto the writable mount
    _drop_privileges(libc)


def _proc_read_only(libc: ctypes.CDLL) -> None:
    """Bind each of :data:`PROC_READ_ONLY` onto itself, read-only. Where that is refused the
    child is in a user namespace (the service does not run as root), and its root owns nothing
    there to write to: go on; a real root child must not."""
    for path in PROC_READ_ONLY:
        if not os.path.exists(path):
            continue
        try:
            _mount(libc, path, path, None, MS_BIND | MS_REC)
            _read_only(libc, path)
        except OSError:
            if _real_root():
                raise


def _real_root() -> bool:
    """Whether this process's uid 0 is the machine's root (no user namespace in between)."""
    try:
        first = Path("/proc/self/uid_map").read_text().split()
    except OSError:
        return os.getuid() == 0
    return os.getuid() == 0 and first[:2] == ["0", "0"]


def _refuse_to_hide_the_code(hidden: list[Path]) -> None:
    """A hidden folder holding the interpreter or the product would leave the child unable to
    import what it runs next, failing later with a misleading ModuleNotFoundError: say why now."""
    code = {Path(sys.prefix).resolve(), Path(__file__).resolve().parents[2]}
    for folder in hidden:
        inside = sorted(str(p) for p in code if _inside(p, folder))
        if inside:
            raise SandboxUnavailable(f"the sandbox would hide {folder}, which holds {', '.join(inside)}: keep the "
                                     f"store, NDRF_SCRATCH and NDRF_SANDBOX_HIDE outside the installation")


def namespaces() -> dict[str, str]:
    """This process's mount and network namespaces (the parent sends its own to the child)."""
    return {kind: os.readlink(f"/proc/self/ns/{kind}") for kind in ("mnt", "net")}


def _check_namespaces(parent: dict[str, str]) -> None:
    """Guards the machine: never remount anything unless this process is in mount and network
    namespaces other than its parent's, whatever else the parent claimed."""
    mine = namespaces()
    for kind in ("mnt", "net"):
        if kind not in parent or mine[kind] == parent[kind]:
            raise RuntimeError(f"the sandbox expected a {kind} namespace of its own and has its parent's")


def _kernel_cache(libc: ctypes.CDLL, hidden: list[Path], own: str | None) -> None:
    """Dr.Jit's kernel cache. ``own`` (a job's: one folder per API key, kept by the parent): that
    folder, bound writable, so a key's jobs reuse the kernels its earlier jobs compiled and no other
    key's child ever loads them. Otherwise an overlay on the shared cache: cached kernels are read,
    new ones kept in /dev/shm and thrown away with the child."""
    if own:  # seen at /dev/shm/drjit-cache: its own path may be under a folder hidden next
        seen = Path("/dev/shm/drjit-cache")
        seen.mkdir()
        _mount(libc, str(Path(own).resolve()), str(seen), None, MS_BIND | MS_REC)
        kept = os.statvfs(seen).f_flag & _KEPT
        _mount(libc, None, str(seen), None, MS_REMOUNT | MS_BIND | MS_NOSUID | MS_NODEV | MS_NOEXEC | kept)
        os.environ["DRJIT_CACHE_DIR"] = str(seen)
        return
    cache = Path(os.environ.get("DRJIT_CACHE_DIR") or Path.home() / ".drjit").resolve()
    if not cache.is_dir() or any(_inside(cache, folder) for folder in hidden):
        os.environ["DRJIT_CACHE_DIR"] = "/dev/shm/drjit-cache"  # an empty cache of its own
        return
    upper, work = Path("/dev/shm/drjit-upper"), Path("/dev/shm/drjit-work")
    upper.mkdir()
    work.mkdir()
    try:
        _mount(libc, "overlay", str(cache), "overlay", MS_NOSUID | MS_NODEV,
               f"lowerdir={cache},upperdir={upper},workdir={work}")
    except OSError:  # no overlayfs (or not in a user namespace on this kernel): an empty cache of its own
        os.environ["DRJIT_CACHE_DIR"] = "/dev/shm/drjit-cache"


def _drop_privileges(libc: ctypes.CDLL) -> None:
    """No capability left (the mounts above cannot be undone), none to gain (``no_new_privs``)."""
    if libc.prctl(PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) != 0:
        raise OSError(ctypes.get_errno(), "prctl(PR_SET_NO_NEW_PRIVS)")
    libc.prctl(PR_CAP_AMBIENT, PR_CAP_AMBIENT_CLEAR_ALL, 0, 0, 0)
    last = int(Path("/proc/sys/kernel/cap_last_cap").read_text())
    for cap in range(last + 1):
        if libc.prctl(PR_CAPBSET_DROP, cap, 0, 0, 0) != 0:
            raise OSError(ctypes.get_errno(), f"prctl(PR_CAPBSET_DROP, {cap})")

    class Header(ctypes.Structure):
        _fields_ = [("version", ctypes.c_uint32), ("pid", ctypes.c_int)]

    class Data(ctypes.Structure):
        _fields_ = [("effective", ctypes.c_uint32), ("permitted", ctypes.c_uint32),
                    ("inheritable", ctypes.c_uint32)]

    header, data = Header(0x20080522, 0), (Data * 2)()        # _LINUX_CAPABILITY_VERSION_3: all zero
    if libc.capset(ctypes.byref(header), data) != 0:
        raise OSError(ctypes.get_errno(), "capset")


def capabilities() -> str:
    """This process's effective capabilities (hex, from /proc): ``0`` once :func:`enter` ran."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("CapEff:"):
            return line.split()[1].lstrip("0") or "0"
    return "?"

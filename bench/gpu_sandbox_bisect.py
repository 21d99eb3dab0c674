"""Which step of the child's sandbox (services/jobs/sandbox.py, enter) hides the GPU from CUDA.

Each step runs alone in fresh namespaces (``unshare``, as the service starts its children), then
the same process asks torch and Dr.Jit for CUDA. One device call:
    run(command="python3 bench/gpu_sandbox_bisect.py", carry=[".gpu"], timeout_s=200)
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

STEPS = ("none", "read_only", "shm", "hide", "kernel_cache", "drop", "all_but_drop", "enter", "limits", "limits_enter")


def _step(name: str, work: Path) -> None:
    from services.jobs import sandbox as s

    libc = s._libc()
    if name in ("read_only", "all_but_drop"):
        for point in s._mount_points():
            try:
                s._read_only(libc, point)
            except OSError as exc:
                print(f"  read-only {point}: {exc}")
    if name in ("shm", "all_but_drop"):
        s._mount(libc, "tmpfs", "/dev/shm", "tmpfs", s.MS_NOSUID | s.MS_NODEV, f"size={s.SHM_BYTES},mode=1777")
    if name in ("hide", "all_but_drop"):
        for folder in (work.parent, Path("/run")):
            s._mount(libc, "tmpfs", str(folder), "tmpfs", s.MS_NOSUID | s.MS_NODEV | s.MS_NOEXEC, "size=64k,mode=755")
    if name in ("kernel_cache", "all_but_drop"):
        s._kernel_cache(libc, [], None)
    if name == "drop":
        s._drop_privileges(libc)
    if name in ("limits", "limits_enter"):   # as services.jobs.isolation.apply_limits does, first
        from services.jobs.isolation import apply_limits
        sandbox = {"namespaces": name == "limits_enter", "hide": [str(work.parent)], "parent_ns": json_ns(),
                   "kernel_cache": None}
        apply_limits({"memory_bytes": 8 << 30, "open_files": 512, "file_bytes": 2 << 30, "sandbox": sandbox})
    if name == "enter":
        s.enter({"namespaces": True, "hide": [str(work.parent)], "parent_ns": json_ns(), "kernel_cache": None})


def json_ns() -> dict:
    return {"mnt": os.environ["PARENT_MNT"], "net": os.environ["PARENT_NET"]}


def child(name: str) -> None:
    work = Path.cwd()
    if name.startswith("ro:"):       # one mount point read-only, as step 1 of enter() does to all
        from services.jobs import sandbox as s

        s._read_only(s._libc(), name[3:])
        import drjit as dr

        print(f"{name:40s} drjit {dr.has_backend(dr.JitBackend.CUDA)}", flush=True)
        return
    _step(name, work)
    import drjit as dr
    import torch

    print(f"{name:14s} torch {torch.cuda.is_available()} drjit {dr.has_backend(dr.JitBackend.CUDA)} "
          f"DRJIT_CACHE_DIR={os.environ.get('DRJIT_CACHE_DIR')}", flush=True)


def main() -> None:
    from services.jobs.sandbox import ROOT_FLAGS, namespaces

    env = {**os.environ, "PARENT_MNT": namespaces()["mnt"], "PARENT_NET": namespaces()["net"],
           "PYTHONPATH": os.pathsep.join([str(Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")])}
    base = Path(tempfile.mkdtemp(prefix="bisect-"))
    if "--mounts" in sys.argv:
        from concurrent.futures import ThreadPoolExecutor

        from services.jobs.sandbox import _mount_points

        lines = Path("/proc/self/mountinfo").read_text().splitlines()
        print("\n".join(" ".join(line.split()[4:]) for line in lines))

        def one(point: str) -> str:
            done = subprocess.run(["unshare", *ROOT_FLAGS, "--", sys.executable, __file__, "ro:" + point], env=env,
                                  capture_output=True, text=True, timeout=120)
            return done.stdout.strip() or f"ro:{point}: exit {done.returncode}: {done.stderr.strip()[-300:]}"

        with ThreadPoolExecutor(8) as pool:
            print("\n".join(pool.map(one, _mount_points())), flush=True)
        return
    for name in STEPS:
        work = base / name / "work"
        work.mkdir(parents=True)
        done = subprocess.run(["unshare", *ROOT_FLAGS, "--", sys.executable, __file__, name], cwd=work, env=env,
                              capture_output=True, text=True, timeout=120)
        print(done.stdout.strip() or f"{name}: exit {done.returncode}: {done.stderr.strip()[-600:]}", flush=True)
        if done.returncode and done.stdout:
            print(done.stderr.strip()[-600:])


if __name__ == "__main__":
    child(sys.argv[1]) if len(sys.argv) > 1 and sys.argv[1] != "--mounts" else main()

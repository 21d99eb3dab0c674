"""``python -m bench.investigations.sandbox_tools``: keep the child's ctypes sandbox, or use bubblewrap (issue 45)?

``services/jobs/sandbox.py`` starts a child through util-linux ``unshare`` and then, inside it,
remounts, hides and drops privileges with ctypes calls (:func:`services.jobs.sandbox.enter`).
``bwrap`` (bubblewrap) does the same from one command line. Measured, in one process, alternating
the variants ``--reps`` times each (median and range of the start-to-exit wall time of a child
that does nothing, the venv's ``python``):

* ``none``: ``python -c pass``, no sandbox (the floor);
* ``unshare``: the product's prefix (:func:`services.jobs.sandbox.command_prefix`) and
  ``python -c pass``: what creating the namespaces costs alone;
* ``unshare+import``: the prefix, and a child that imports :mod:`services.jobs.sandbox` only;
* ``product``: the prefix, and a child that imports :mod:`services.jobs.sandbox` and calls
  :func:`~services.jobs.sandbox.enter` as :func:`services.jobs.isolation.apply_limits` does (a
  scene check's spec: the store and the work folder's parent hidden, the kernel cache an overlay);
* ``bwrap``: the same isolation as one ``bwrap`` command line (:func:`bwrap_command`) and
  ``python -c pass``.

Then a probe child in ``none``, ``product`` and ``bwrap`` asks, one question at a time, what the
sandbox holds: a write outside the work folder, a write in the store, a write in the work folder,
a connection to Redis on 127.0.0.1:6379 and to a Unix socket under ``/run``, a listing of the
store, an unmount of the store's cover, opening ``/proc/sys`` for writing, its capabilities,
``no_new_privs`` and the capabilities of a program it runs (root's regained ones, without
``no_new_privs``), and whether a signal sent to the started process (the runner's SIGUSR1 cancel,
SIGTERM stop, SIGUSR2 images) reaches it. Needs root or unprivileged user namespaces, ``unshare``,
``bwrap`` and a Redis on 127.0.0.1:6379 (the connection row says "refused" without one either way).
Also counts the lines of ``sandbox.py`` that a bwrap backend would replace.
"""

from __future__ import annotations

import argparse
import ast
import json
import logging
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bench.common import markdown_table, write_markdown
from services.jobs import sandbox

ROOT = Path(__file__).resolve().parents[2]
log = logging.getLogger("bench.investigations.sandbox_tools")

#: The child of the ``product`` variant: what ``apply_limits`` does last, then exit.
ENTER = "import json, sys; from services.jobs import sandbox; sandbox.enter(json.loads(sys.argv[1]))"

#: The scale: what every real child pays before it reads a scene.
MITSUBA = "import mitsuba; mitsuba.set_variant('llvm_ad_rgb')"

#: The probe child: optionally ``enter``, then each question; answers one JSON line on stdout.
PROBE = r'''
import ctypes, json, os, signal, socket, sys, time
args = json.loads(sys.argv[1])
if args["enter"]:
    from services.jobs import sandbox
    sandbox.enter(args["enter"])
def attempt(action):
    try:
        return "yes: " + str(action())
    except OSError as exc:
        return "no: " + (exc.strerror or str(exc))
def write(folder):
    path = os.path.join(folder, "probe-%d" % os.getpid())
    with open(path, "w") as f:
        f.write("x")
    os.unlink(path)
    return "wrote " + folder
def connect(where):
    if where.startswith("/"):
        with socket.socket(socket.AF_UNIX) as s:
            s.connect(where)
    else:
        with socket.create_connection((where, 6379), timeout=2):
            pass
    return "connected"
def unmount(folder):
    libc = ctypes.CDLL("libc.so.6", use_errno=True)
    if libc.umount2(folder.encode(), 2) != 0:
        e = ctypes.get_errno()
        raise OSError(e, os.strerror(e))
    return "unmounted"
def open_write(path):
    os.close(os.open(path, os.O_WRONLY))
    return "opened"
def open_child_status():
    import subprocess
    return subprocess.run(["/bin/cat", "/proc/self/status"], capture_output=True, text=True).stdout.splitlines()
status = dict(line.split(":", 1) for line in open("/proc/self/status").read().splitlines() if ":" in line)
answer = {
    "write outside the work folder": attempt(lambda: write(args["outside"])),
    "write in the store": attempt(lambda: write(args["store"])),
    "write in the work folder": attempt(lambda: write(".")),
    "connect to Redis 127.0.0.1:6379": attempt(lambda: connect("127.0.0.1")),
    "connect to a Unix socket under /run": attempt(lambda: connect(args["socket"])) if args["socket"] else "n/a",
    "see the store's files": attempt(lambda: sorted(os.listdir(args["store"])) or "empty"),
    "unmount the store's cover": attempt(lambda: unmount(args["store"])),
    "open /proc/sys/kernel/hostname for writing": attempt(lambda: open_write("/proc/sys/kernel/hostname")),
    "effective capabilities": status["CapEff"].strip(),
    "bounding capabilities": status["CapBnd"].strip(),
    "no_new_privs": status.get("NoNewPrivs", "?").strip(),
    "effective capabilities of a program it runs": attempt(lambda: [line.split()[1] for line in open_child_status()
                                                                   if line.startswith("CapEff")][0]),
    "pid 1 in its view": open("/proc/1/comm").read().strip(),
}
got = []
signal.signal(signal.SIGUSR1, lambda *_: got.append(True))
print(json.dumps(answer), flush=True)
deadline = time.monotonic() + 3
while not got and time.monotonic() < deadline:
    time.sleep(0.01)
print(json.dumps({"SIGUSR1 to the started process reaches the child": "yes" if got else "no"}), flush=True)
'''


def bwrap_command(store: Path, work: Path) -> list[str]:
    """The product's isolation as bubblewrap options (the kernel cache aside: bwrap 0.8 has no
    overlay; a run's per-key cache would be one more ``--bind``)."""
    options = ["--unshare-net", "--unshare-ipc", "--ro-bind", "/", "/", "--dev", "/dev", "--proc", "/proc",
               *(arg for path in sandbox.PROC_READ_ONLY for arg in ("--ro-bind-try", path, path)),
               "--tmpfs", "/dev/shm", "--tmpfs", "/run", "--remount-ro", "/run",
               "--tmpfs", str(store), "--remount-ro", str(store),
               "--tmpfs", str(work.parent), "--bind", str(work), str(work), "--remount-ro", str(work.parent),
               "--chdir", str(work), "--cap-drop", "ALL", "--new-session", "--die-with-parent"]
    return [shutil.which("bwrap") or "bwrap", *options, "--"]


def run_once(command: list[str], cwd: Path, env: dict[str, str]) -> float:
    start = time.perf_counter()
    done = subprocess.run(command, cwd=cwd, env=env, stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL,
                          stderr=subprocess.PIPE, start_new_session=True, close_fds=True)
    seconds = time.perf_counter() - start
    if done.returncode != 0:
        raise RuntimeError(f"{command[0]} exited {done.returncode}: {done.stderr.decode()[-400:]}")
    return seconds


def probe(command: list[str], enter: dict | None, folders: dict, cwd: Path, env: dict[str, str]) -> dict:
    args = {"enter": enter, **folders}
    proc = subprocess.Popen([*command, sys.executable, "-c", PROBE, json.dumps(args)], cwd=cwd, env=env,
                            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line:
        raise RuntimeError(f"probe failed: {proc.communicate()[1][-400:]}")
    answer = json.loads(line)
    proc.send_signal(signal.SIGUSR1)
    out, _ = proc.communicate(timeout=10)
    answer.update(json.loads(out.splitlines()[0]) if out.strip() else
                  {"SIGUSR1 to the started process reaches the child": f"no (exit {proc.returncode})"})
    return answer


#: What a bwrap backend would replace in ``services/jobs/sandbox.py``: the child's half (the mounts,
#: the namespace guard, the capabilities). What stays: the policy, the probe, ``_inside`` and
#: ``_refuse_to_hide_the_code`` (moved to the parent), ``PROC_READ_ONLY`` (bwrap options), ``capabilities``.
REPLACED = ("_libc", "_mount", "_mount_points", "_read_only", "enter", "_proc_read_only", "_real_root",
            "namespaces", "_check_namespaces", "_drop_privileges",
            "MS_RDONLY", "_KEPT", "_PSEUDO", "PR_SET_NO_NEW_PRIVS")
#: Replaced in part: the per-key bind is one ``--bind``; the overlay has no bwrap 0.8 option.
PARTLY = ("_kernel_cache",)


def line_counts() -> dict:
    path = ROOT / "services" / "jobs" / "sandbox.py"
    source = path.read_text()
    tree = ast.parse(source)
    sizes: dict[str, int] = {}
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.ClassDef)):
            name = node.name
        elif isinstance(node, ast.Assign) and isinstance(node.targets[0], (ast.Name, ast.Tuple)):
            target = node.targets[0]
            name = target.id if isinstance(target, ast.Name) else getattr(target.elts[0], "id", "")
        else:
            continue
        start = min([node.lineno, *(d.lineno for d in getattr(node, "decorator_list", []))])
        sizes[name] = (node.end_lineno or node.lineno) - start + 1
    return {"total": len(source.splitlines()), "replaced": sum(sizes.get(n, 0) for n in REPLACED),
            "partly": sum(sizes.get(n, 0) for n in PARTLY), "replaced_names": list(REPLACED),
            "partly_names": list(PARTLY)}


def non_root() -> dict[str, str]:
    """Whether each tool makes its namespaces for an unprivileged uid (65534) on this machine."""
    setpriv = shutil.which("setpriv")
    if os.geteuid() != 0 or setpriv is None:
        return {}
    drop = [setpriv, "--reuid", "65534", "--regid", "65534", "--clear-groups"]
    tries = {"unshare " + " ".join(sandbox.USER_FLAGS): [shutil.which("unshare") or "unshare", *sandbox.USER_FLAGS,
                                                          "true"],
             "bwrap --unshare-user --unshare-net --ro-bind / /": ["bwrap", "--unshare-user", "--unshare-net",
                                                                  "--ro-bind", "/", "/", "true"]}
    answers = {}
    for name, command in tries.items():
        done = subprocess.run([*drop, *command], capture_output=True, text=True, timeout=20, cwd="/")
        answers[name] = "works" if done.returncode == 0 else f"fails: {done.stderr.strip()[-200:]}"
    return answers


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.sandbox_tools", description=__doc__)
    parser.add_argument("--reps", type=int, default=30)
    parser.add_argument("--mitsuba-reps", type=int, default=5,
                        help="runs of a bare child that imports Mitsuba and sets a variant (the scale: what a "
                             "real child pays before it reads a scene)")
    parser.add_argument("--note", default="", help="what the results page says of the machine (shared, loaded)")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "sandbox_tools.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    prefix = list(sandbox.command_prefix("required"))
    bwrap_version = subprocess.run(["bwrap", "--version"], capture_output=True, text=True).stdout.strip()
    env = {"PATH": os.environ.get("PATH", "/usr/bin:/bin"), "PYTHONPATH": str(ROOT), "PYTHONHASHSEED": "0",
           "HOME": os.environ.get("HOME", "/root")}
    with tempfile.TemporaryDirectory(prefix="sandbox-tools-") as tmp:
        base = Path(tmp).resolve()
        store, work = base / "store", base / "scratch" / "job"
        store.mkdir()
        (store / "record.json").write_text("{}")
        work.mkdir(parents=True)
        (base / "scratch" / "other-job").mkdir()
        spec = {"namespaces": True, "hide": [str(store), str(work.parent)], "parent_ns": sandbox.namespaces(),
                "kernel_cache": None}
        python = [sys.executable, "-c"]
        variants = {"none": [*python, "pass"],
                    "unshare": [*prefix, *python, "pass"],
                    "unshare+import": [*prefix, *python, "from services.jobs import sandbox"],
                    "product": [*prefix, *python, ENTER, json.dumps(spec)],
                    "bwrap": [*bwrap_command(store, work), *python, "pass"]}
        for command in variants.values():  # warm-up: the page cache, and a failing variant fails here
            run_once(command, work, env)
        times: dict[str, list[float]] = {name: [] for name in variants}
        for _ in range(args.reps):
            for name, command in variants.items():
                times[name].append(run_once(command, work, env))
        scale = [run_once([*python, MITSUBA], work, {**env, "DRJIT_LIBLLVM_PATH": os.environ.get(
            "DRJIT_LIBLLVM_PATH", "")}) for _ in range(args.mitsuba_reps)]
        folders = {"outside": str(base), "store": str(store),
                   "socket": next((str(s) for s in Path("/run").rglob("*.sock") if s.is_socket()), "")}
        probes = {"none": probe([], None, folders, work, env),
                  "product": probe(prefix, spec, folders, work, env),
                  "bwrap": probe(bwrap_command(store, work), None, folders, work, env)}
    timing = {name: {"median_ms": 1000 * statistics.median(t), "min_ms": 1000 * min(t), "max_ms": 1000 * max(t)}
              for name, t in times.items()}
    mitsuba = {"median_ms": 1000 * statistics.median(scale), "min_ms": 1000 * min(scale),
               "max_ms": 1000 * max(scale), "reps": len(scale), "child": MITSUBA} if scale else None
    results = {"reps": args.reps, "mitsuba_child": mitsuba, "unshare": " ".join(prefix), "bwrap": bwrap_version,
               "bwrap_command": " ".join(bwrap_command(Path("<store>"), Path("<scratch>/<job>"))),
               "product_child": ENTER, "timing": timing, "probes": probes, "lines": line_counts(),
               "non_root": non_root(), "note": args.note}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    floor = timing["none"]["median_ms"]
    rows = [[name, f"{t['median_ms']:.1f}", f"{t['min_ms']:.1f}-{t['max_ms']:.1f}", f"{t['median_ms'] - floor:+.1f}"]
            for name, t in timing.items()]
    table = markdown_table(["variant", "median ms", "range ms", "over none, ms"], rows)
    questions = list(probes["none"])
    parity = markdown_table(["question", *probes], [[q, *(str(p.get(q, "")) for p in probes.values())]
                                                     for q in questions])
    lines = results["lines"]
    text = (f"Start-to-exit wall time of `python -c pass`, {args.reps} runs of each variant, alternating"
            f"{f' ({args.note})' if args.note else ''}. `unshare`: `{results['unshare']}`; "
            f"`bwrap` ({bwrap_version}): `{results['bwrap_command']}`.\n\n{table}\n\n"
            + (f"For scale: a bare child that only imports Mitsuba and sets `llvm_ad_rgb` takes "
               f"{mitsuba['median_ms']:.0f} ms (median of {mitsuba['reps']}, {mitsuba['min_ms']:.0f}-"
               f"{mitsuba['max_ms']:.0f}), no sandbox.\n\n" if mitsuba else "")
            + f"What the child can do, per variant:\n\n{parity}\n\n"
            f"`services/jobs/sandbox.py`: {lines['total']} lines; a bwrap backend would replace "
            f"{lines['replaced']} ({', '.join(lines['replaced_names'])}) and {lines['partly']} in part "
            f"({', '.join(lines['partly_names'])}).\n\nAn unprivileged uid (65534): "
            + ("; ".join(f"`{k}` {v}" for k, v in results["non_root"].items()) or "not tried (not root)") + "\n")
    write_markdown(args.out, "bench.investigations.sandbox_tools", argv, text)
    log.info("%s", text)


if __name__ == "__main__":
    main()

"""Shared pieces of the benchmarks: the machine, problems, errors, timing."""

from __future__ import annotations

import os
import platform
import subprocess
import time
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np


def _lines(path: str) -> list[str]:
    try:
        with open(path) as handle:
            return handle.readlines()
    except OSError:
        return []


def machine() -> dict:
    """What the numbers were measured on: the machine and the device the solver runs on
    (``NDRF_DEVICE``, :func:`services.solver.backend.describe_device`)."""
    cpu = platform.processor() or platform.machine()
    for line in _lines("/proc/cpuinfo"):
        if line.startswith("model name"):
            cpu = line.split(":", 1)[1].strip()
            break
    memory = None
    for line in _lines("/proc/meminfo"):
        if line.startswith("MemTotal"):
            memory = f"{int(line.split()[1]) / 2**20:.1f} GiB"
    import drjit
    import mitsuba
    import torch

    from services.solver.backend import describe_device

    device = describe_device()
    try:   # a lent GPU machine gets a copy of the tree, perhaps without git
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True).stdout.strip()
    except OSError:
        commit = ""
    return {"cpu": cpu, "cores": os.cpu_count(), "memory": memory, "python": platform.python_version(),
            "mitsuba": mitsuba.__version__, "drjit": drjit.__version__, "torch": torch.__version__,
            "device": device["device"], "device_name": device["name"], "commit": commit or None}


def relative_error(g: np.ndarray, reference: np.ndarray) -> float:
    return float(np.linalg.norm(g - reference) / max(np.linalg.norm(reference), 1e-30))


@dataclass
class Clock:
    """Accumulates wall seconds spent inside ``with clock:`` blocks."""

    seconds: float = 0.0
    _start: float = field(default=0.0, repr=False)

    def __enter__(self):
        self._start = time.perf_counter()
        return self

    def __exit__(self, *exc):
        self.seconds += time.perf_counter() - self._start


@contextmanager
def timed():
    clock = Clock()
    with clock:
        yield clock


def problem(scene: str, keys: list[str], resolution=(64, 64), method: str | None = None):
    """A Problem for a built-in scene, planned for ``method`` when given."""
    from services.solver.backend import use_mitsuba, use_torch

    use_mitsuba(), use_torch()
    from services.solver.estimators.methods import method_class
    from services.solver.estimators.problem import Problem
    from services.solver.scene.effects import choose_effects
    from services.solver.scene.facts import probe_scene
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    loaded = load_scene(builtin=scene, resolution=resolution)
    prob = Problem(loaded, ParameterSet(loaded.params, keys))
    if method is not None:
        prob.simulate(choose_effects(probe_scene(loaded, prob.parameters), method, method_class(method).uses))
    return prob


def loop_rows(job: dict, run) -> tuple[dict, int]:
    """``run(prepared)`` on the job prepared for :mod:`bench.mitsuba_loop`, with its scene freed
    before this returns: returns ``(run's result, number of target views)``.

    Dr.Jit traces a virtual call (a BSDF's, a shape's) over every live instance of its class, so a
    second scene alive in the process makes every render of the first slower: about 20% per
    ``prb`` iteration on room-open-8 (``python -m bench.prb_iteration``'s docstring). The product
    runs one scene per process (a child per job); a bench that kept the loop's scene alive while
    the product runs would charge the product for the bench's own scene."""
    import gc

    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare

    prepared, _ = prepare(JobSpec.model_validate(job))
    try:
        return run(prepared), len(prepared.targets)
    finally:
        del prepared
        gc.collect()


def markdown_table(header: list[str], rows: list[list]) -> str:
    def cell(v):
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return str(v).replace("|", "\\|")   # a cell's own bar (|error|) would end it

    lines = ["| " + " | ".join(cell(h) for h in header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def chosen(names: str, known, parser, what: str) -> list[str]:
    """The comma-separated ``names`` of a command line, each one of ``known`` (else a usage error
    that lists them)."""
    picked = [n.strip() for n in names.split(",") if n.strip()]
    for name in picked:
        if name not in known:
            parser.error(f"unknown {what} {name!r}; known: {', '.join(known)}")
    return picked


def write_markdown(out, module: str, argv: list[str] | None, text: str) -> None:
    """``out`` with suffix ``.md``: the machine and the command that made it (``python -m module ARGS``),
    then ``text`` (``python -m bench.docs`` reads the machine line)."""
    import sys
    from pathlib import Path

    command = " ".join(sys.argv[1:] if argv is None else argv)
    stamp = ", ".join(f"{k} {v}" for k, v in machine().items() if v is not None)
    Path(out).with_suffix(".md").write_text(f"Machine: {stamp}\nCommand: `python -m {module} {command}`\n\n{text}\n")

"""Where an NDRF iteration's time goes, by sampling profiler.

    py-spy record --format raw --rate 200 -o /tmp/steps.txt -- \
        python -m bench.investigations.profile_step --iterations 30
    python -m bench.investigations.profile_step --summarize /tmp/steps.txt

The first command runs ``examples/demo.json`` as written with ``"method": "ndrf-lhs"`` (its other
settings the defaults, the warm-up cut to 20 steps) for ``--iterations`` iterations under py-spy;
the second keeps the samples inside the loop's iterations, groups them by the innermost project
frame (or by the autograd engine, for the backward pass) and prints the share of each part as a
markdown table.
"""

from __future__ import annotations

import argparse
import json
import logging
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
log = logging.getLogger("bench.investigations.profile_step")

#: (substring of a frame's file, part of an iteration), first match from the innermost frame outwards
PARTS = (
    ("services/solver/fields/encoding", "hash-grid encoding (corner lookup, blend)"),
    ("services/solver/fields/", "fields: MLP and inputs"),
    ("services/solver/sampling/", "sampling and BSDF/emitter evaluation (Mitsuba/Dr.Jit)"),
    ("services/solver/scene/params", "forward-mode AD of bsdf.eval / emitter.eval"),
    ("services/solver/training/residuals", "residual assembly"),
    ("services/solver/training/pool", "residual pool (draws, re-evaluation)"),
    ("services/solver/training/", "training loop (loss, Adam, weight averaging)"),
    ("services/solver/estimators/render", "candidate render (path tracer)"),
    ("services/solver/estimators/methods/", "camera pass (gradient and Jacobian)"),
    ("services/solver/optimize/", "parameter step, estimate, records"),
)
#: a sample is inside an iteration when one of its frames is this (the loop's iteration; py-spy
#: qualifies it with its class)
ITERATION = "_iteration"


def _name(frame: str) -> str:
    """A py-spy frame's bare function name: ``Class.method (file:line)`` -> ``method``."""
    return frame.partition(" (")[0].rpartition(".")[2]


def summarize(path: Path) -> str:
    """Markdown table of the step-time shares in a py-spy ``raw`` (collapsed stacks) file."""
    counts: Counter[str] = Counter()
    for line in path.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        frames = stack.split(";")
        names = [_name(f) for f in frames]
        if ITERATION not in names:
            continue                                       # start-up, scene loading, targets
        if any(name in ("backward", "_engine_run_backward") for name in names):
            part = "backward pass (autograd)"
        else:
            part = next((name for f in reversed(frames) for key, name in PARTS if key in f), "other")
        counts[part] += int(n)
    total = sum(counts.values()) or 1
    rows = [f"| {part} | {100 * c / total:.0f}% |" for part, c in counts.most_common()]
    return "\n".join(["| part of an iteration | share of samples |", "|---|---|", *rows,
                      f"\n{total} samples inside iterations"])


def run(iterations: int) -> None:
    from bench.regime import merge, run_product

    job = json.loads((ROOT / "examples" / "demo.json").read_text())
    run_product(merge(job, {"method": "ndrf-lhs", "training": {"warmup_steps": 20}}), 0.0, iterations=iterations)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=30, help="iterations to run")
    parser.add_argument("--summarize", type=Path, help="summarize a py-spy raw profile instead of training")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    if args.summarize:
        log.info("%s", summarize(args.summarize))
    else:
        run(args.iterations)


if __name__ == "__main__":
    main()

"""Where a training step's time goes, by sampling profiler.

    py-spy record --format raw --rate 200 -o /tmp/steps.txt -- python -m bench.profile_step --steps 60
    python -m bench.profile_step --summarize /tmp/steps.txt

The first command trains both fields of the Cornell box (red wall, default configuration) for
``--steps`` steps under py-spy; the second groups the samples that fall inside training steps by
the innermost project frame (or by the autograd engine, for the backward pass) and prints the
share of each part as a markdown table.
"""

from __future__ import annotations

import argparse
from collections import Counter
from pathlib import Path

#: (substring of a frame's file, part of the step), first match from the innermost frame outwards
PARTS = (
    ("services/fields/encoding", "hash-grid encoding (forward)"),
    ("services/fields/mlp", "MLP (forward)"),
    ("services/fields/", "field inputs (normalisation, SH, caching)"),
    ("services/sampling/", "sampling and BSDF/emitter evaluation (Mitsuba/Dr.Jit)"),
    ("services/scene/params", "forward-mode AD of bsdf.eval / emitter.eval"),
    ("services/solver/estimators/residuals", "residual assembly"),
    ("services/solver/estimators/", "training loop (loss, optimizer step)"),
)


def summarize(path: Path) -> str:
    """Markdown table of the step-time shares in a py-spy ``raw`` (collapsed stacks) file."""
    counts: Counter[str] = Counter()
    for line in path.read_text().splitlines():
        stack, _, n = line.rpartition(" ")
        frames = stack.split(";")
        if not any("services/solver/estimators/training" in f for f in frames):
            continue                                       # start-up, scene loading, compilation
        if any(f.startswith(("backward ", "_engine_run_backward ")) for f in frames):
            part = "backward pass (autograd)"
        else:
            part = next((name for f in reversed(frames) for key, name in PARTS if key in f), "other")
        counts[part] += int(n)
    total = sum(counts.values()) or 1
    rows = [f"| {part} | {100 * c / total:.0f}% |" for part, c in counts.most_common()]
    return "\n".join(["| part of a training step | share of samples |", "|---|---|", *rows,
                      f"\n{total} samples inside training steps"])


def train(steps: int) -> None:
    from bench.common import problem
    from schemas.solver import TrainingConfig
    from services.solver.training.trainer import FieldTrainer

    prob = problem("cornell-box", ["red.reflectance.value"], method="ndrf-rhs")
    trainer = FieldTrainer(prob, TrainingConfig(), radiance=True, differential=True, seed=0)
    trainer.train(steps)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=60, help="training steps to run")
    parser.add_argument("--summarize", type=Path, help="summarize a py-spy raw profile instead of training")
    args = parser.parse_args(argv)
    if args.summarize:
        print(summarize(args.summarize))
    else:
        train(args.steps)


if __name__ == "__main__":
    main()

"""A figure of finished jobs: the target, the first gradient image, parameter trajectories.

    python -m bench.job_figure runs/hidden-rhs runs/hidden-rc --out docs/assets/hidden-object.png

Each argument is a job folder (``ndrf run ... --out DIR`` or the service's store). The first row
shows the first job's target image and, per job, its iteration-0 gradient image dI/dp of the first
scalar (diverging colour map, one shared scale clipped at the 99th percentile, so a zero gradient
is visibly white); the second row plots every job's parameter values against the iteration, with
the synthetic target dashed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from bench.report import pyplot, save
from services.store.job import JobFiles
from services.store.local import FolderStore

CHANNEL_COLORS = ("#dc2626", "#16a34a", "#2563eb")


def _trajectory(folder: JobFiles) -> tuple[np.ndarray, np.ndarray]:
    """(iterations K, parameter values K x P) including the value after the last step."""
    records = [folder.iteration_record(k) for k in folder.iterations()]
    values = [r["parameters"] for r in records] + [records[-1]["updated_parameters"]]
    return np.arange(len(values)), np.asarray(values, dtype=float)


def job_figure(folders: list[Path], out: Path) -> None:
    plt = pyplot()
    jobs = [JobFiles(FolderStore(Path(f).resolve().parent), Path(f).resolve().name) for f in folders]
    specs = [job.read("spec.json") for job in jobs]
    first = jobs[0]
    gradients = [np.load(j.store.local_path(j.iteration_key(j.iterations()[0], "gradients.npy")))[0].sum(axis=-1)
                 for j in jobs]
    scale = max(float(np.percentile(np.abs(g), 99)) for g in gradients) or 1.0    # robust to fireflies

    fig = plt.figure(figsize=(3.0 * (len(jobs) + 1), 6.4))
    grid = fig.add_gridspec(2, len(jobs) + 1, height_ratios=(1.0, 1.1))
    ax = fig.add_subplot(grid[0, 0])
    target = np.load(first.store.local_path(first.target_key(0, "npy")))
    ax.imshow(np.clip(target / max(np.percentile(target, 99.5), 1e-8), 0, 1) ** (1 / 2.2))
    ax.set_title("target", fontsize=9)
    ax.axis("off")
    for i, (spec, g) in enumerate(zip(specs, gradients)):
        ax = fig.add_subplot(grid[0, i + 1])
        ax.imshow(g, cmap="RdBu_r", vmin=-scale, vmax=scale)
        ax.set_title(f"{spec['method']}: dI/dp[0], iteration 0\nmax |.| = {np.abs(g).max():.2e}", fontsize=9)
        ax.axis("off")

    ax = fig.add_subplot(grid[1, :])
    target_values = np.asarray(first.read("summary.json").get("target_values") or [], dtype=float)
    styles = ("-", ":", "-.", "--")
    for j, (job, spec) in enumerate(zip(jobs, specs)):
        k, values = _trajectory(job)
        for c in range(values.shape[1]):
            ax.plot(k, values[:, c], styles[j % len(styles)], color=CHANNEL_COLORS[c % 3], lw=1.6,
                    label=f"{spec['method']} [{c}]")
    for c, value in enumerate(target_values):
        ax.axhline(value, color=CHANNEL_COLORS[c % 3], lw=0.8, ls="--", alpha=0.6)
    ax.set_xlabel("iteration")
    ax.set_ylabel(specs[0]["parameters"][0]["key"])
    ax.set_title("parameter values (dashed: target)", fontsize=9)
    ax.grid(True, alpha=0.25)
    ax.legend(fontsize=7, ncol=len(jobs), loc="center right")
    save(fig, out)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folders", type=Path, nargs="+", help="job folders, the first one's target is shown")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    args = parser.parse_args(argv)
    job_figure(args.folders, args.out)


if __name__ == "__main__":
    main()

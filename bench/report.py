"""Tables (markdown) and plots (PNG) of the benchmark results."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from bench.common import markdown_table

COLORS = {"prb": "#111827", "direct": "#9ca3af", "radiance-cache": "#f59e0b", "ndrf-lhs": "#2563eb",
          "ndrf-rhs": "#dc2626"}


def pareto(points: list[dict]) -> list[dict]:
    """Lower-left envelope: each point's error is the best reached at or before its time."""
    front, best = [], float("inf")
    for p in sorted(points, key=lambda p: p["seconds"]):
        if p["error"] < best:
            best = p["error"]
            front.append(p)
    return front


def pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: Path) -> None:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    pyplot().close(fig)


def accuracy_plot(results: dict, path: Path) -> None:
    plt = pyplot()
    scenes = list(results)
    fig, axes = plt.subplots(1, len(scenes), figsize=(5.2 * len(scenes), 4.2), squeeze=False)
    for ax, scene in zip(axes[0], scenes):
        points = results[scene]["points"]
        for method in COLORS:
            mine = [p for p in points if p["method"] == method]
            if not mine:
                continue
            ax.scatter([p["seconds"] for p in mine], [p["error"] for p in mine], s=10, color=COLORS[method], alpha=0.35)
            front = pareto(mine)
            ax.plot([p["seconds"] for p in front], [p["error"] for p in front], "-o", ms=3, color=COLORS[method],
                    label=method)
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.set_title(f"{scene}: {results[scene]['key']}", fontsize=10)
        ax.set_xlabel("seconds (training + query, or sampling)")
        ax.set_ylabel("relative L2 error of dI/dp vs prb")
        ax.grid(True, which="both", alpha=0.25)
        ax.legend(fontsize=8)
    save(fig, path)


def accuracy_table(results: dict) -> str:
    parts = []
    for scene, data in results.items():
        rows = []
        for method in COLORS:
            mine = [p for p in data["points"] if p["method"] == method]
            for p in pareto(mine):
                rows.append([method, p["spp"], p.get("steps", 0), p["seconds"], p["error"]])
        parts.append(f"**{scene}** (`{data['key']}`: {data['shows']}; reference prb at {data['reference_spp']} spp, "
                     f"{data['reference_seconds']:.0f} s). Pareto-optimal points per method:\n\n"
                     + markdown_table(["method", "spp", "training steps", "seconds", "rel. error"], rows))
    return "\n\n".join(parts)


def depth_plot(data: dict, path: Path) -> None:
    plt = pyplot()
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.8))
    rows = [r for r in data["rows"] if r["method"] == "prb"]
    left.plot([r["depth"] for r in rows], [r["seconds"] for r in rows], "-o", color=COLORS["prb"], label="prb")
    right.plot([r["depth"] for r in rows], [r["sum_error"] for r in rows], "-o", color=COLORS["prb"], label="prb")
    for r in (r for r in data["rows"] if r["method"] == "ndrf-rhs"):     # no depth parameter: one measurement
        label = "ndrf-rhs (no max depth; one measurement)"
        left.axhline(r["seconds"], color=COLORS["ndrf-rhs"], ls="--", label=label)
        right.axhline(r["sum_error"], color=COLORS["ndrf-rhs"], ls="--", label=label)
    left.set_xlabel("max path depth")
    left.set_ylabel("seconds per iteration (gradient)")
    right.set_xlabel("max path depth")
    right.set_ylabel("rel. error of pixel-summed dI/dp\nvs prb at depth 64")
    right.set_yscale("log")
    for ax in (left, right):
        ax.grid(True, alpha=0.25)
        ax.legend(fontsize=8)
    fig.suptitle("hidden-object (closed room): cost and error against path length", fontsize=10)
    save(fig, path)


def depth_table(data: dict) -> str:
    rows = [[r["method"], "none (one bounce + fields)" if r["depth"] is None else r["depth"], r["seconds"], r["error"],
             r["sum_error"], r.get("note", f"{data['spp']}-spp gradient")] for r in data["rows"]]
    return markdown_table(["method", "max depth", "seconds / iteration", "rel. error (images)",
                           "rel. error (pixel sum)", "what an iteration is"], rows)


def scaling_plot(data: dict, path: Path) -> None:
    plt = pyplot()
    rows = data["rows"]
    fig, (left, right) = plt.subplots(1, 2, figsize=(10, 3.6))
    x = [r["scalars"] for r in rows]
    left.plot(x, [r["step_seconds"] for r in rows], "-o", color=COLORS["ndrf-rhs"], label="training step")
    left.plot(x, [r["differential_seconds"] for r in rows], "--o", color=COLORS["ndrf-lhs"], label="of which dL_theta")
    right.plot(x, [r["peak_rss_mib"] for r in rows], "-o", color=COLORS["prb"])
    for ax in (left, right):
        ax.set_xscale("log", base=2)
        ax.set_xlabel("optimized scalars")
        ax.grid(True, alpha=0.25)
    left.set_ylabel("seconds")
    left.legend(fontsize=8)
    right.set_ylabel("peak resident memory (MiB)")
    save(fig, path)


def scaling_table(data: dict) -> str:
    rows = [[r["scalars"], r["outputs"], r["step_seconds"], r["differential_seconds"], r["peak_rss_mib"]]
            for r in data["rows"]]
    return markdown_table(["scalars", "dL_theta outputs", "s / training step", "s / dL_theta step", "peak RSS MiB"], rows)


def e2e_plot(data: dict, path: Path) -> None:
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 4))
    for method, run in data.items():
        curve = run["curve"]
        ax.plot([c["seconds"] for c in curve], [c["error"] for c in curve], "-", color=COLORS[method], label=method)
    ax.set_xlabel("seconds")
    ax.set_ylabel("max |albedo - target| of the hidden sphere")
    ax.set_title("hidden-object: inverse rendering, error against time", fontsize=10)
    ax.grid(True, alpha=0.25)
    ax.legend(fontsize=8)
    save(fig, path)


def e2e_table(data: dict) -> str:
    rows = []
    for method, run in data.items():
        last = run["curve"][-1] if run["curve"] else {"seconds": float("nan"), "error": float("nan")}
        rows.append([method, run["status"], len(run["curve"]), last["seconds"], last["error"],
                     ", ".join(f"{v:.3f}" for v in run["final"] or [])])
    return markdown_table(["method", "status", "iterations", "seconds", "final max error", "final albedo"], rows)


def fmt_ratio(a: float, b: float) -> str:
    return f"{a / b:.1f}x" if b > 0 and np.isfinite(a / b) else "-"

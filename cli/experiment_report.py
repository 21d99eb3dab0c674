"""How an experiment is shown in a terminal and on disk: the runs table, the mean and spread per
configuration, the comparison table of ``ndrf compare``, and an SVG plot of accuracy against
time (no plotting library: a few dozen lines of SVG, readable in any browser and on GitHub).

Everything here works on the API's JSON documents (experiment, runs, curves), so the same code
shows an experiment run in-process and one fetched from a server.
"""

from __future__ import annotations

import html
import math
from pathlib import Path

PALETTE = ["#2563eb", "#dc2626", "#16a34a", "#9333ea", "#ea580c", "#0891b2", "#ca8a04", "#db2777"]


def fmt(value, digits: int = 4) -> str:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}g}"
    return str(value)


def mean_std(metric: dict | None, digits: int = 3) -> str:
    if not metric or metric.get("mean") is None:
        return "-"
    text = fmt(metric["mean"], digits)
    return text if metric.get("std") is None else f"{text} ± {fmt(metric['std'], 2)}"


def runs_table(experiment: dict, rows: list[dict]):
    """One line per run, best first by the objective."""
    from rich.table import Table

    column = {"parameter_error": "final_parameter_error", "loss": "final_loss", "seconds": "seconds",
              "time_to_error": "time_to_error"}[experiment["objective"]["metric"]]
    reverse = experiment["objective"]["goal"] == "max"
    ordered = sorted(rows, key=lambda r: (r.get(column) is None, -(r.get(column) or 0) if reverse
                                          else (r.get(column) or 0)))
    varied = [p for p in experiment["varied"] if p != "seed"]
    table = Table(title=f"{experiment.get('name') or experiment['id']}: {experiment['status']}, "
                        f"{len(rows)} runs (best first by {column})")
    for name in ("run", *varied, "seed", "status", "iter", "final error", "final loss", "seconds",
                 f"t(err≤{experiment['sweep'].get('target_error', 0.05):g})"):
        table.add_column(name, justify="left" if name in ("status", *varied) else "right")
    for row in ordered:
        table.add_row(str(row["index"]), *[fmt(row["varied"].get(p)) for p in varied], fmt(row.get("seed")),
                      row["status"], f"{row.get('iterations', 0)}/{fmt(row.get('iterations_planned'))}",
                      fmt(row.get("final_parameter_error")), fmt(row.get("final_loss")), fmt(row.get("seconds"), 3),
                      fmt(row.get("time_to_error"), 3))
    return table


def aggregates_table(experiment: dict):
    """Mean ± standard deviation over seeds per configuration."""
    from rich.table import Table

    groups = experiment.get("aggregates") or []
    table = Table(title="mean ± std over seeds (succeeded runs)")
    names = sorted({k for g in groups for k in g["configuration"]})
    for name in (*names, "runs", "final error", "final loss", "seconds",
                 f"t(err≤{experiment['sweep'].get('target_error', 0.05):g})"):
        table.add_column(name, justify="left" if name in names else "right")
    for group in groups:
        metrics = group["metrics"]
        reached = metrics["time_to_error"]
        table.add_row(*[fmt(group["configuration"].get(n)) for n in names], f"{group['succeeded']}/{group['runs']}",
                      mean_std(metrics["final_parameter_error"]), mean_std(metrics["final_loss"]),
                      mean_std(metrics["seconds"]),
                      f"{mean_std(reached)} ({int(reached['n'])}/{group['runs']})" if reached["n"] else "not reached")
    return table


# ------------------------------------------------------------------------------------ SVG


def _ticks_log(lo: float, hi: float) -> list[float]:
    """Decades, with 2 and 5 between them when the axis spans less than two decades."""
    multiples = (1, 2, 5) if hi - lo < 2 else (1,)
    ticks = [m * 10.0 ** d for d in range(math.floor(lo), math.ceil(hi) + 1) for m in multiples
             if lo - 1e-9 <= math.log10(m) + d <= hi + 1e-9]
    if len(ticks) < 2:                      # within one octave: plain values
        ticks = [v for v in _ticks_linear(10 ** lo, 10 ** hi, 4) if v > 0]
    return ticks


def _ticks_linear(lo: float, hi: float, count: int = 5) -> list[float]:
    raw = (hi - lo) / max(count, 1) or 1.0
    magnitude = 10 ** math.floor(math.log10(raw))
    step = min((m * magnitude for m in (1, 2, 5, 10)), key=lambda s: abs(s - raw))
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step) + 1)]


def _panel(curves: list[dict], key: str, title: str, x0: float, width: float, height: float) -> list[str]:
    """One log-y panel of ``key`` against seconds, a line per curve (with its spread band)."""
    margin = {"left": 62, "right": 14, "top": 28, "bottom": 40}
    pw, ph = width - margin["left"] - margin["right"], height - margin["top"] - margin["bottom"]
    curves = [_with_start(c, key) for c in curves]
    points = [(t, v) for c in curves for t, v in zip(c["seconds"], c[key]) if v is not None and v > 0]
    out = [f'<text x="{x0 + width / 2}" y="18" text-anchor="middle" font-weight="600">{html.escape(title)}</text>']
    if not points:
        return out + [f'<text x="{x0 + width / 2}" y="{height / 2}" text-anchor="middle">no data</text>']
    tmax = max(t for t, _ in points) or 1.0
    lo, hi = math.log10(min(v for _, v in points)), math.log10(max(v for _, v in points))
    if hi - lo < 0.5:
        lo, hi = lo - 0.25, hi + 0.25
    sx = lambda t: x0 + margin["left"] + t / tmax * pw
    sy = lambda v: margin["top"] + (1 - (math.log10(v) - lo) / (hi - lo)) * ph
    axis_y = margin["top"] + ph
    out.append(f'<line x1="{sx(0)}" y1="{axis_y}" x2="{sx(tmax)}" y2="{axis_y}" stroke="#94a3b8"/>')
    for t in _ticks_linear(0, tmax):
        out.append(f'<text x="{sx(t):.1f}" y="{axis_y + 16}" text-anchor="middle">{fmt(t, 3)}</text>')
    for v in _ticks_log(lo, hi):
        out.append(f'<line x1="{sx(0)}" x2="{sx(tmax)}" y1="{sy(v):.1f}" y2="{sy(v):.1f}" stroke="#e2e8f0"/>')
        out.append(f'<text x="{sx(0) - 6}" y="{sy(v) + 4:.1f}" text-anchor="end">{fmt(v, 2)}</text>')
    out.append(f'<text x="{sx(tmax / 2)}" y="{height - 6}" text-anchor="middle">compute seconds</text>')
    for i, curve in enumerate(curves):
        color = PALETTE[i % len(PALETTE)]
        spread = curve.get(f"{key}_spread") or []
        band = [(t, s) for t, s in zip(curve["seconds"], spread) if s and s[0] > 0 and s[1] > 0]
        if len(band) > 1:
            path = [f"{sx(t):.1f},{sy(s[1]):.1f}" for t, s in band] + \
                   [f"{sx(t):.1f},{sy(s[0]):.1f}" for t, s in reversed(band)]
            out.append(f'<polygon points="{" ".join(path)}" fill="{color}" fill-opacity="0.12" stroke="none"/>')
        kept = [(t, v) for t, v in zip(curve["seconds"], curve[key]) if v is not None and v > 0]
        if key == "parameter_error":       # a step: the parameters change at the end of each iteration
            kept = [p for (t0, v0), (t1, _) in zip(kept, kept[1:]) for p in ((t0, v0), (t1, v0))] + kept[-1:]
        line = [f"{sx(t):.1f},{sy(v):.1f}" for t, v in kept]
        if line:
            out.append(f'<polyline points="{" ".join(line)}" fill="none" stroke="{color}" stroke-width="2"/>')
    return out


def _with_start(curve: dict, key: str) -> dict:
    """The parameter error curve starts at 0 s with the initial error."""
    start = curve.get("initial_parameter_error") if key == "parameter_error" else None
    if start is None or not curve["seconds"]:
        return curve
    spread = curve.get(f"{key}_spread")
    return {**curve, "seconds": [0.0, *curve["seconds"]], key: [start, *curve[key]],
            f"{key}_spread": None if spread is None else [[start, start], *spread]}


TITLE_CHARS = 100


def accuracy_svg(curves: list[dict], title: str, path: Path) -> Path:
    """Parameter error and loss against compute seconds, one line per curve (mean over seeds,
    shaded from the best to the worst seed), log y."""
    width, height, legend = 960, 380, 26 * ((len(curves) + 3) // 4)
    if len(title) > TITLE_CHARS:  # what fits in the width at 14 px
        title = title[:TITLE_CHARS - 1].rstrip() + "…"
    parts = [f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height + legend + 30}" '
             f'font-family="system-ui, sans-serif" font-size="12" fill="#0f172a">',
             '<rect width="100%" height="100%" fill="#ffffff"/>',
             f'<text x="{width / 2}" y="16" text-anchor="middle" font-size="14" font-weight="650">'
             f'{html.escape(title)}</text>', '<g transform="translate(0, 20)">']
    parts += _panel(curves, "parameter_error", "max |p − target|", 0, width / 2, height)
    parts += _panel(curves, "loss", "image loss", width / 2, width / 2, height)
    parts.append("</g>")
    for i, curve in enumerate(curves):
        x, y = 70 + (i % 4) * 220, height + 40 + (i // 4) * 26
        color = PALETTE[i % len(PALETTE)]
        parts.append(f'<rect x="{x}" y="{y - 9}" width="18" height="4" fill="{color}"/>')
        parts.append(f'<text x="{x + 24}" y="{y - 4}">{html.escape(curve["label"])}</text>')
    parts.append("</svg>")
    path.write_text("\n".join(parts) + "\n")
    return path

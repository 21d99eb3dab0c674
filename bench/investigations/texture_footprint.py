"""A texture the images cannot pin down: the recipe's choice of resolution against the alternatives.

``python -m bench.investigations.texture_footprint [--iterations 200] [--seeds 0,1,2]
[--variants auto,full,laplacian,coarse]``

The user's job of the issue: the textured box's 64 x 64 back-wall albedo (12,288 scalars) seen by
its 4 views at 64 x 64 pixels (about 1,300 wall pixels each: fewer pixels than texels), the
targets uploaded as images (rendered once from the true texture at ``--target-spp``), and a job
that names only the scene, the texture, the targets, ``prb`` and the iterations. Variants differ
only in ``textures``:

``auto``       the default: the recipe measures the footprint and matches the resolution to it
``full``       ``resolution: "full"``: every texel free (the product before the footprint rule)
``laplacian``  ``full`` with the Laplacian smoothness prior (weight 0.01, the best of bench.textures)
``coarse``     ``full`` with a 3-level coarse-to-fine schedule

Reported per variant, median and range over ``--seeds``: the PSNR of the returned texture (the
estimate) and of the last iterate against the true texture, and the median and 95th percentile
of the per-texel standard error; ``bench/results/texture_footprint.png`` shows, for the first
seed, the truth, each variant's estimate, its error and its standard-error map.
"""

from __future__ import annotations

import argparse
import base64
import json
import logging
import tempfile
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
KEY = "wall.reflectance.data"
FILM = 64
VARIANTS = {"auto": {}, "full": {"resolution": "full"},
            "laplacian": {"resolution": "full", "smoothness": "laplacian", "smoothness_weight": 0.01},
            "coarse": {"resolution": "full", "coarse_to_fine": 3}}


def psnr(value: np.ndarray, truth: np.ndarray) -> float:
    return float(10.0 * np.log10(1.0 / np.mean((np.asarray(value, np.float64) - truth) ** 2)))


def targets(spp: int) -> dict:
    """The 4 views of the true texture at ``FILM`` x ``FILM``, as uploaded images (base64 npy)."""
    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare
    from services.store.images import npy_bytes

    spec = JobSpec.model_validate({"scene": {"builtin": "textured-box"}, "parameters": [{"key": KEY}],
                                   "targets": {"synthetic": {"values": {KEY: None}, "spp": spp}},
                                   "render": {"resolution": [FILM, FILM]}})
    prepared, _ = prepare(spec)
    return {"images": [{"sensor": s, "data": base64.b64encode(npy_bytes(np.asarray(image, np.float32))).decode()}
                       for s, image in sorted(prepared.targets.items())]}


def run(variant: str, seed: int, iterations: int, images: dict) -> dict:
    from schemas.job import JobSpec
    from services.jobs.local import run_local
    from services.solver.scene.textured import true_albedo

    truth = true_albedo().astype(np.float64)
    job = {"scene": {"builtin": "textured-box"}, "parameters": [{"key": KEY, "init": 0.5}], "targets": images,
           "method": "prb", "iterations": iterations, "seed": seed, "render": {"resolution": [FILM, FILM]},
           "textures": VARIANTS[variant]}
    with tempfile.TemporaryDirectory() as tmp:
        summary = run_local(JobSpec.model_validate(job), Path(tmp) / "job")
        folder, files = Path(tmp) / "job", summary["textures"][KEY]
        final, last = np.load(folder / files["npy"]), np.load(folder / files["last"])
        se = np.load(folder / files["standard_error"]) if files.get("standard_error") else None
        plan = json.loads((folder / "plan.json").read_text())
    chosen = next((d for d in plan["recipe"]["decisions"] if d["what"] == f"resolution {KEY}"), None)
    out = {"variant": variant, "seed": seed, "status": summary["status"], "iterations": summary["iterations"],
           "seconds": summary["seconds"], "psnr": psnr(final, truth), "last_psnr": psnr(last, truth),
           "resolution": chosen["value"] if chosen else None, "final": final, "se": se,
           "pinned": float(np.mean((final <= 0.0) | (final >= 1.0)))}
    if se is not None:
        out["se_median"], out["se_p95"] = float(np.median(se)), float(np.percentile(se, 95))
        z = np.abs(final - truth) / np.maximum(se, 1e-12)
        out["coverage_2se"], out["median_z"] = float(np.mean(z <= 2)), float(np.median(z))
    log.info("%s seed %d: %.2f dB (last iterate %.2f dB), resolution %s", variant, seed, out["psnr"], out["last_psnr"],
             out["resolution"])
    return out


def figure(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from services.solver.scene.textured import true_albedo

    truth = true_albedo()
    fig, axes = plt.subplots(len(rows), 4, figsize=(10, 2.6 * len(rows)), squeeze=False)
    for ax_row, row in zip(axes, rows):
        error = np.abs(row["final"] - truth).mean(-1)
        se = row["se"].mean(-1) if row["se"] is not None else np.zeros_like(error)
        top = max(float(error.max()), float(se.max()), 1e-6)
        panels = [(truth, "truth"), (np.clip(row["final"], 0, 1), f"{row['variant']}: {row['psnr']:.1f} dB"),
                  (error, "|error| (mean over RGB)"), (se, "standard error (mean over RGB)")]
        for ax, (image, title) in zip(ax_row, panels):
            ax.imshow(image, vmin=0, vmax=1 if image.ndim == 3 else top, cmap=None if image.ndim == 3 else "magma")
            ax.set_title(title, fontsize=8)
            ax.axis("off")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.texture_footprint", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=200)
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--target-spp", type=int, default=1024)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "texture_footprint.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    images = targets(args.target_spp)
    seeds = [int(s) for s in args.seeds.split(",")]
    rows = [run(v.strip(), seed, args.iterations, images) for v in args.variants.split(",") for seed in seeds]
    figure([r for r in rows if r["seed"] == seeds[0]], args.out.with_suffix(".png"))
    table = []
    for variant in dict.fromkeys(r["variant"] for r in rows):
        mine = [r for r in rows if r["variant"] == variant]

        def spread(key: str, fmt: str = ".2f", mine=mine) -> str:
            values = [r[key] for r in mine if r.get(key) is not None]
            return f"{np.median(values):{fmt}} ({min(values):{fmt}}-{max(values):{fmt}})" if values else "-"

        table.append([variant, mine[0]["resolution"] or "-", spread("psnr"), spread("last_psnr"),
                      spread("pinned", ".3f"), spread("se_median", ".4f"), spread("se_p95", ".4f"),
                      spread("coverage_2se", ".2f"), spread("median_z"), spread("seconds", ".0f")])
    text = markdown_table(["variant", "resolution", "PSNR of the answer (dB)", "PSNR of the last iterate (dB)",
                           "texels at a bound", "median SE", "95th percentile SE", "coverage of ±2 SE",
                           "median |error|/SE", "seconds"], table)
    for r in rows:
        r.pop("final")
        r.pop("se")
    args.out.write_text(json.dumps({"machine": machine(), "rows": rows}, indent=1))
    picture = f"\n\n![truth, answer, error and standard error]({args.out.stem}.png)"
    write_markdown(args.out, "bench.investigations.texture_footprint", argv, text + picture)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

"""``ndrf gradient``: gradient images of one method at a job's initial parameters."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from cli.common import read_job
from schemas.methods import Method

log = logging.getLogger(__name__)


@click.command("gradient")
@click.option("--job", "job_path", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Job file (only scene, parameters, render and targets are used).")
@click.option("--method", type=click.Choice([m.value for m in Method]), required=True, help="Gradient method.")
@click.option("--spp", type=click.IntRange(1, 1 << 20), default=None,
              help="Samples per pixel of the gradient query (default: render.gradient_spp).")
@click.option("--train-steps", type=click.IntRange(0, 10**6), default=None,
              help="Training steps of the fields before the query (default: training.warmup_steps).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Output folder.")
def gradient_command(job_path: str, method: str, spp: int | None, train_steps: int | None, out_dir: str) -> None:
    """Evaluate dI/dp and dz/dp at the job's initial parameter values.

    Writes OUT/gradients.npy (float32, P x H x W x 3), OUT/gradient-<i>.png (diverging colour map,
    red = positive) and OUT/summary.json with the method, the seconds spent and dz/dp.
    """
    from schemas.errors import InvalidJob
    from services.jobs.preflight import upload_limits
    from services.settings import Limits
    from services.solver.optimize.evaluate import evaluate_gradient
    from services.store.files import atomic_write_bytes, atomic_write_json, atomic_write_npy
    from services.store.images import gradient_png
    from services.uploads.staging import stage_scene

    spec = read_job(job_path)
    out = Path(out_dir)
    try:
        scene_file = stage_scene(spec.scene, out / "scene", upload_limits(Limits()), Path(job_path).resolve().parent)
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    try:
        result = evaluate_gradient(spec, method, spp=spp, train_steps=train_steps, scene_file=scene_file)
    except InvalidJob as exc:
        raise click.ClickException(f"{exc.field}: {exc.message}") from None
    summary = result.summary
    for sensor, images in sorted(result.images.items()):
        folder = out if sensor == 0 else out / f"sensor-{sensor}"
        atomic_write_npy(folder / "gradients.npy", images.astype("float32"))
        scales = []
        for i in range(images.shape[0]):
            png, scale = gradient_png(images[i])
            atomic_write_bytes(folder / f"gradient-{i}.png", png)
            scales.append(scale)
        summary.setdefault("preview_scales", scales)
    atomic_write_json(out / "summary.json", summary)
    click.echo(f"{method}: {summary['seconds']:.1f} s (training {summary['training_seconds']:.1f} s)")
    for label, value in zip(summary["labels"], summary["dz_dp"]):
        click.echo(f"  dz/d{label} = {value:+.6e}")
    click.echo(f"wrote {out_dir}/gradients.npy, {len(summary['labels'])} PNG preview(s), summary.json")

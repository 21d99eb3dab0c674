"""``ndrf gradient``: gradient images of one method at a job's initial parameters."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from schemas.job import METHOD_NAMES
from cli.common import read_job

log = logging.getLogger(__name__)


@click.command("gradient")
@click.option("--job", "job_path", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Job file (only scene, parameters, render and targets are used).")
@click.option("--method", type=click.Choice(METHOD_NAMES), required=True, help="Gradient method.")
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
    from services.optimize.gradient import evaluate_gradient

    spec = read_job(job_path)
    summary = evaluate_gradient(spec, method, Path(out_dir), spp=spp, train_steps=train_steps,
                                base_dir=Path(job_path).resolve().parent)
    click.echo(f"{method}: {summary['seconds']:.1f} s (training {summary['training_seconds']:.1f} s)")
    for label, value in zip(summary["labels"], summary["dz_dp"]):
        click.echo(f"  dz/d{label} = {value:+.6e}")
    click.echo(f"wrote {out_dir}/gradients.npy, {len(summary['labels'])} PNG preview(s), summary.json")

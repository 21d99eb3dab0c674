"""``ndrf gradient``: gradient images of one method at a job's initial parameters."""

from __future__ import annotations

import logging
from pathlib import Path

import click

from cli.common import read_job
from schemas.methods import Method

log = logging.getLogger(__name__)

#: Samples per pixel of the images ``ndrf gradient`` writes: one image a user looks at, not a step of
#: the inverse loop, whose 1-spp ``render.gradient_spp`` serves an optimizer that averages noise over
#: iterations. ``python -m bench.investigations.gradient_spp`` (hidden-object, ``ndrf-rhs``, 250 warm-up steps,
#: against ``prb`` at 2 x 2048 spp, whose own noise is 0.09): the image's relative error is 2.82 at
#: 1 spp, 0.66 at 16, 0.35 at 64, 0.19 at 256, 0.13 at 1024, falling as 1/sqrt(spp) (noise, not the
#: field's bias, dominates throughout). So the cost decides: the query took 12 s at 64 spp beside
#: 518 s of training (57 s at 256, 256 s at 1024); an earlier run, 9 s at 64 beside 220 s.
GRADIENT_SPP = 64


@click.command("gradient")
@click.option("--job", "job_path", type=click.Path(exists=True, dir_okay=False), required=True,
              help="Job file (only scene, parameters, render and targets are used).")
@click.option("--method", type=click.Choice([m.value for m in Method]), required=True, help="Gradient method.")
@click.option("--spp", type=click.IntRange(1, 1 << 20), default=GRADIENT_SPP, show_default=True,
              help="Samples per pixel of the gradient images, whatever the job's render.gradient_spp (1 by "
                   "default: it serves an optimizer that averages noise over iterations). On hidden-object the "
                   "ndrf-rhs image's error relative to prb's is 2.8 at 1 spp and 0.35 at 64, for 2 to 4% of the "
                   "command's time (python -m bench.investigations.gradient_spp, two runs).")
@click.option("--train-steps", type=click.IntRange(0, 10**6), default=None,
              help="Training steps of the fields before the query (default: the job's training.warmup_steps, "
                   "what the inverse loop's first step queries).")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Output folder.")
def gradient_command(job_path: str, method: str, spp: int, train_steps: int | None, out_dir: str) -> None:
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
    from services.uploads.staging import stage_job

    spec = read_job(job_path)
    out = Path(out_dir)
    try:
        scene_file = stage_job(spec, out / "scene", upload_limits(Limits()), Path(job_path).resolve().parent)
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

"""``ndrf view JOB_DIR --out DIR``: a job's fields rendered from a camera no sensor had, in-process
(the job folder is the user's own, as with ``ndrf run``)."""

from __future__ import annotations

import json
import tempfile
from pathlib import Path

import click
from pydantic import ValidationError

from schemas.job import JobSpec, PathScene
from schemas.validation import describe
from schemas.views import ViewRequest


def _request(options: dict) -> ViewRequest:
    body = {k: v for k, v in options.items() if v is not None and v != ()}
    try:
        return ViewRequest.model_validate(body)
    except ValidationError as exc:
        lines = "\n".join(f"  {field}: {msg}" for field, msg in describe(exc))
        raise click.ClickException(f"invalid view\n{lines}") from None


@click.command("view")
@click.argument("job_dir", type=click.Path(exists=True, file_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Folder for the view's files.")
@click.option("--sensor", type=int, help="Start from this scene sensor (default 0 without --origin).")
@click.option("--offset", type=float, nargs=3, help="Move the sensor's camera by X Y Z (world units).")
@click.option("--origin", type=float, nargs=3, help="A free camera's position X Y Z (with --target).")
@click.option("--target", type=float, nargs=3, help="The point a free camera looks at.")
@click.option("--up", type=float, nargs=3, help="A free camera's up direction (default 0 1 0).")
@click.option("--fov", type=float, help="A free camera's horizontal field of view, degrees (default 40).")
@click.option("--resolution", type=int, nargs=2, help="Film WIDTH HEIGHT (default: the job's).")
@click.option("--spp", type=int, help="First-hit samples per pixel (default 4).")
@click.option("--prb-spp", type=int, help="Also prb's gradient images from the same camera at this spp.")
@click.option("--seed", type=int, help="Seed of the pixel samples.")
@click.option("--scene", "scene_path", type=click.Path(exists=True, dir_okay=False),
              help="The XML of a job whose scene was a local path (the job folder does not hold it).")
def view_command(job_dir: str, out_dir: str, scene_path: str | None, **options) -> None:
    """Render L_phi and each scalar's dL_theta of the job in JOB_DIR (its checkpoints/latest.pt)
    from a camera; writes radiance.npy/.png, gradients.npy, gradient-<p>.png, prb.npy and
    prb-<p>.png with --prb-spp, and view.json into OUT."""
    from services.jobs.preflight import upload_limits
    from services.jobs.views import view_files
    from services.settings import Limits
    from services.solver.optimize.field_views import render_view, restore
    from services.uploads.staging import stage_job

    folder = Path(job_dir)
    if options["origin"] is None and options["sensor"] is None:
        options["sensor"] = 0
    request = _request(options)
    spec_file, checkpoint = folder / "spec.json", folder / "checkpoints" / "latest.pt"
    if not spec_file.is_file() or not checkpoint.is_file():
        raise click.ClickException(f"{folder} has no spec.json and checkpoints/latest.pt: not a job folder with a "
                                   f"checkpoint")
    spec = JobSpec.model_validate_json(spec_file.read_bytes())
    with tempfile.TemporaryDirectory(prefix="ndrf-view-") as tmp:
        if isinstance(spec.scene, PathScene):
            if scene_path is None:
                raise click.ClickException("the job's scene is a local path: give it with --scene")
            scene_file: Path | None = Path(scene_path)
        else:
            scene_file = stage_job(spec, Path(tmp) / "scene", upload_limits(Limits()))
        try:
            restored = restore(spec, checkpoint.read_bytes(), scene_file)
            view = render_view(restored, request)
        except ValueError as exc:
            raise click.ClickException(str(exc)) from None
    meta = {"scalars": view.scalars, "seconds": view.seconds, "camera": view.camera, "iteration": restored.iteration,
            "method": restored.method, "request": request.model_dump(mode="json")}
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, data in view_files(view.radiance, view.gradients, view.prb, meta).items():
        (out / name).write_bytes(data)
    click.echo(json.dumps({"out": str(out), "seconds": view.seconds, "scalars": view.scalars}))

"""``ndrf run``: an inverse-rendering job in-process (the embedded default), with progress."""

from __future__ import annotations

import json
import math
from pathlib import Path

import click

from cli.common import read_job


def _progress_hooks(total: int):
    """Rich progress bar fed by the run's events (iteration, loss, ETA)."""
    from rich.progress import (
        BarColumn,
        MofNCompleteColumn,
        Progress,
        TextColumn,
        TimeElapsedColumn,
        TimeRemainingColumn,
    )

    progress = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                        TextColumn("loss {task.fields[loss]}"), TimeElapsedColumn(), TextColumn("ETA"),
                        TimeRemainingColumn())
    task = progress.add_task("starting", total=total, loss="-")

    def on_event(event: dict) -> None:
        kind = event["type"]
        if kind == "iteration":
            progress.update(task, completed=event["iteration"] + 1, description="optimizing",
                            loss=f"{event['loss']:.4g}")
        elif kind == "preparing":
            progress.update(task, description=event["what"])
        elif kind == "resumed":
            progress.update(task, completed=event["iteration"], description="resumed")
        elif kind == "warmup":
            residual = event.get("residual_differential") or event.get("residual_radiance")
            progress.update(task, description=f"warm-up {event['steps']}/{event['planned']} steps"
                                              + (f", residual {residual:.3g}" if residual is not None else ""))
        elif kind == "plan":
            progress.update(task, description="training fields" if any(event["plan"]["fields"].values()) else "optimizing")

    return progress, on_event


def _texture_row(key: str, files: dict, out: Path, init: dict | None) -> tuple[list[str], str]:
    """A texture's row of the final table (its mean per channel: initial from the plan's summary
    ``init``, estimate, target) and a caption line (the file, and the PSNR against a synthetic
    target), from the job folder ``out``."""
    import numpy as np

    from services.solver.optimize.textures import texture_error

    def mean(summary_or_array) -> str:
        values = summary_or_array["mean"] if isinstance(summary_or_array, dict) else summary_or_array.mean(axis=(0, 1))
        return " ".join(f"{float(v):.3f}" for v in np.atleast_1d(values))

    final = np.load(out / files["npy"])
    target = np.load(out / files["target"]) if files.get("target") and (out / files["target"]).exists() else None
    label = f"{key} ({'x'.join(str(n) for n in final.shape)} texture, mean)"
    row = [label, mean(init) if init else "", mean(final), mean(target) if target is not None else "-"]
    caption = f"{key}: {files['npy']}"
    if target is not None:
        caption += f", PSNR {texture_error(final, target)['psnr']:.2f} dB against the target"
    return row, caption


def _final_table(summary: dict, out: Path):
    """The answer as a table, from ``summary.json`` (of this version or an older one)."""
    from rich.table import Table

    from schemas.summary import Summary

    summary = Summary.read(summary).model_dump()

    table = Table(title=f"{summary['method']}: {summary['status']} after {summary['iterations']} iterations "
                        f"({summary['seconds']:.0f} s)")
    for column in ("parameter", "init", "estimate ± standard error", "target"):
        table.add_column(column, justify="left" if column == "parameter" else "right")
    scalars = summary["scalars"] or []
    targets = summary.get("target_values") or [math.nan] * len(scalars)
    errors = summary.get("standard_error") or [None] * len(scalars)
    for label, init, estimate, error, target in zip(scalars, summary["init"], summary["estimate"], errors, targets):
        value = f"{estimate:.4f}" + ("" if error is None else f" ± {error:.4f}")
        table.add_row(label, f"{init:.4f}", value, "-" if target is None or math.isnan(target) else f"{target:.4f}")
    captions = []
    textures = summary.get("textures") or {}
    plan = json.loads((out / "plan.json").read_text()) if textures and (out / "plan.json").exists() else {}
    inits = {t["key"]: t.get("init") for t in plan.get("textures") or []}
    for key, files in textures.items():
        row, caption = _texture_row(key, files, out, inits.get(key))
        table.add_row(*row)
        captions.append(caption)
    for shape, mesh in (summary.get("meshes") or {}).items():
        chamfer = mesh.get("chamfer")
        table.add_row(f"{shape}.vertex_positions ({mesh['vertices']} vertices)", "", mesh["file"],
                      "-" if chamfer is None else f"Chamfer {chamfer:.4f}")
        captions.append(f"{shape}: {mesh['file']}" + ("" if chamfer is None else
                                                       f", Chamfer distance {chamfer:.4g} to the target surface"))
    stopped = summary.get("stopped") or {}
    if summary.get("estimate_window"):
        first, last = summary["estimate_window"]
        captions.append(f"estimate: from iterations {first} to {last} ({summary['estimate_kind']}); the last "
                        f"iterate is summary.json's last_iterate")
    if stopped.get("reason"):
        captions.append(f"stopped: {stopped['reason']}")
    table.caption = "\n".join(captions) or None
    return table


@click.command("run")
@click.argument("job_path", type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Job folder for the artifacts.")
@click.option("--resume", is_flag=True, help="Continue a killed or interrupted run from its last checkpoint in OUT.")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def run_command(job_path: str, out_dir: str, resume: bool, quiet: bool) -> None:
    """Recover the job's parameters in-process; artifacts go to OUT (see README, 'Job folder').
    Ctrl-C stops at the next training step with a checkpoint: continue with --resume."""
    import signal

    from rich.console import Console

    from services.jobs.local import OutFolderInUse, run_local

    spec = read_job(job_path)
    console = Console(stderr=True)
    interrupted: list[str] = []
    previous = signal.signal(signal.SIGINT, lambda *_: interrupted.append("interrupted"))
    stop = lambda: interrupted[0] if interrupted else None
    try:
        if quiet:
            summary = run_local(spec, Path(out_dir), base_dir=Path(job_path).resolve().parent, resume=resume,
                                should_stop=stop)
        else:
            progress, on_event = _progress_hooks(spec.iterations)
            with progress:
                summary = run_local(spec, Path(out_dir), base_dir=Path(job_path).resolve().parent, resume=resume,
                                    on_event=on_event, should_stop=stop)
    except OutFolderInUse as exc:
        raise click.ClickException(str(exc)) from None
    finally:
        signal.signal(signal.SIGINT, previous)
    if summary.get("estimate") is not None:
        console.print(_final_table(summary, Path(out_dir)))
    if summary["status"] == "interrupted":
        raise click.ClickException(f"interrupted after {summary['iterations']} iteration(s): continue with "
                                   f"ndrf run {job_path} --out {out_dir} --resume")
    if summary["status"] != "succeeded":
        raise click.ClickException(f"job {summary['status']}: {summary.get('error') or ''}".strip())
    console.print(f"artifacts in {out_dir}")

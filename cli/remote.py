"""``ndrf submit | watch | fetch | ls --server URL``: a running server, through :mod:`client`.

The key comes from ``NDRF_API_KEY``, the server from ``--server`` or ``NDRF_SERVER``. ``watch``
follows a job's or an experiment's event stream with a progress bar (warm-up included) and
reconnects with ``Last-Event-ID`` when the connection drops.
"""

from __future__ import annotations

import json
from pathlib import Path

import click

from cli.experiment_report import fmt, runs_table
from client import ApiError, Client, is_experiment_id, pack_scene
from client.scenes import SceneError
from schemas.files import mesh_name

server_option = click.option("--server", default="http://127.0.0.1:8000", show_default=True, envvar="NDRF_SERVER",
                             help="The server's URL (or NDRF_SERVER); the key is NDRF_API_KEY.")


def _client(server: str) -> Client:
    return Client.from_env(server)


def _fail(exc: ApiError) -> click.ClickException:
    return click.ClickException("\n  ".join([f"the server refused ({exc.status}):", *exc.lines()]))


# --------------------------------------------------------------------------- watch


def _watch_job(api: Client, job_id: str, quiet: bool) -> str:
    from cli.run import _progress_hooks

    job = api.job(job_id)
    if quiet:
        for _ in api.events(job_id):
            pass
        return api.job(job_id)["status"]
    progress, on_event = _progress_hooks(job["iterations"])
    status = job["status"]
    with progress:
        for event in api.events(job_id):
            if event.get("type") == "status":
                status = event["status"]
                if status in ("queued", "running") and event.get("note"):
                    progress.console.print(f"{status}: {event['note']}")
                continue
            on_event(event)
    return api.job(job_id)["status"]


def _watch_experiment(api: Client, exp_id: str, quiet: bool) -> str:
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    experiment = api.experiment(exp_id)
    statuses = {row["index"]: row["status"] for row in api.runs(exp_id)}
    progress = Progress(TextColumn("[bold]runs"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                        TextColumn("{task.description}"), disable=quiet)
    task = progress.add_task("", total=experiment["runs"])

    def show():
        done = sum(s in ("succeeded", "failed", "canceled") for s in statuses.values())
        running = sorted(i for i, s in statuses.items() if s == "running")
        progress.update(task, total=len(statuses), completed=done,
                        description=f"running {', '.join(f'#{i}' for i in running)}" if running else "")

    with progress:
        show()
        for event in api.events(exp_id):
            if event.get("type") == "run":
                statuses[event["index"]] = event["status"]
            elif event.get("type") in ("appended", "retry"):
                for index in event.get("runs", []):
                    statuses[index] = "pending"
            show()
    return api.experiment(exp_id)["status"]


def watch(api: Client, resource_id: str, quiet: bool = False) -> str:
    return (_watch_experiment if is_experiment_id(resource_id) else _watch_job)(api, resource_id, quiet)


@click.command("watch")
@click.argument("resource_id")
@server_option
@click.option("--quiet", is_flag=True, help="No progress bar; only the final status.")
def watch_command(resource_id: str, server: str, quiet: bool) -> None:
    """Follow a job or an experiment until it finishes (progress bar, warm-up included)."""
    api = _client(server)
    try:
        status = watch(api, resource_id, quiet)
        if is_experiment_id(resource_id):
            from rich.console import Console

            Console().print(runs_table(api.experiment(resource_id), api.runs(resource_id)))
    except ApiError as exc:
        raise _fail(exc) from None
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"{resource_id}: {status}")
    if status != "succeeded":
        raise SystemExit(1)


# -------------------------------------------------------------------------- submit


@click.command("submit")
@click.argument("path", type=click.Path(exists=True, dir_okay=False))
@server_option
@click.option("--watch", "follow", is_flag=True, help="Follow it until it finishes.")
@click.option("--idempotency-key", default=None, help="Retrying with the same key returns the same job.")
def submit_command(path: str, server: str, follow: bool, idempotency_key: str | None) -> None:
    """Submit a job file or an experiment file (it has a "base") to a server; prints the id. A
    local {"path": ...} scene is sent with the files it names."""
    api = _client(server)
    try:
        document = pack_scene(json.loads(Path(path).read_text(encoding="utf-8")), Path(path).resolve().parent)
    except (SceneError, ValueError, OSError) as exc:
        raise click.ClickException(f"{path}: {exc}") from None
    try:
        if "base" in document:
            kind, accepted = "experiment", api.submit_experiment(document)
        else:
            kind, accepted = "job", api.submit_job(document, idempotency_key)
        click.echo(f"{kind} {accepted['id']} {accepted['status']}"
                   + (f" ({accepted['runs']} runs)" if kind == "experiment" else ""))
        if follow:
            status = watch(api, accepted["id"])
            click.echo(f"{accepted['id']}: {status}")
    except ApiError as exc:
        raise _fail(exc) from None


def run_remote(server: str, document: dict, base_dir: Path, quiet: bool) -> tuple[dict, list[dict], dict]:
    """Submit an experiment, follow it, and return its document, rows and curves (ndrf compare)."""
    api = _client(server)
    try:
        accepted = api.submit_experiment(pack_scene(document, base_dir))
        watch(api, accepted["id"], quiet)
        return api.experiment(accepted["id"]), api.runs(accepted["id"]), api.curves(accepted["id"])
    except ApiError as exc:
        raise _fail(exc) from None
    except SceneError as exc:
        raise click.ClickException(str(exc)) from None


# --------------------------------------------------------------------------- fetch


def fetch_job(api: Client, job_id: str, out: Path, all_images: bool = False) -> list[Path]:
    """The job's record, iteration records, target images, the images of the last iteration that
    wrote them (every such iteration with ``all_images``), its latest checkpoint and its answer's
    files: recovered textures, meshes and poses (``final/``, as ``ndrf run`` writes them)."""
    base = f"/v1/jobs/{job_id}"
    out.mkdir(parents=True, exist_ok=True)
    job = api.job(job_id)
    records = api.iterations(job_id)
    written = [_write_json(out / "job.json", job), _write_json(out / "iterations.json", records)]
    plan = job.get("plan") or {}
    for sensor in plan.get("sensors") or [0]:
        for ext in ("png", "exr"):   # a job begun before targets had an .exr has none: skipped
            written += _maybe(api, f"{base}/targets/{sensor}.{ext}", out / "targets" / f"target-{sensor}.{ext}")
    with_images = [r["iteration"] for r in records if r.get("images")]
    for k in with_images if all_images else with_images[-1:]:
        folder = out / "iterations" / f"{k:06d}"
        written += _maybe(api, f"{base}/iterations/{k}/render.png", folder / "render.png")
        written += _maybe(api, f"{base}/iterations/{k}/gradients.npy", folder / "gradients.npy")
        for p in range(len(plan.get("scalars") or [])):
            written += _maybe(api, f"{base}/iterations/{k}/gradients/{p}.png", folder / f"gradient-{p}.png")
    written += _maybe(api, f"{base}/checkpoints/latest", out / "checkpoints" / "latest.pt")
    finals = [f"{texture['key']}.{ext}" for texture in plan.get("textures") or [] for ext in ("npy", "exr")]
    finals += [f"{mesh_name(shape)}.ply" for shape in plan.get("shapes") or {}] + ["poses.json"]
    for name in finals:   # a job that did not get to its end, or has no such parameter, has none: skipped
        written += _maybe(api, f"{base}/final/{name}", out / "final" / name)
    return written


def _maybe(api: Client, path: str, destination: Path) -> list[Path]:
    try:
        return [api.download(path, destination)]
    except ApiError as exc:
        if exc.status == 404:
            return []
        raise


def _write_json(path: Path, value) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value, indent=1) + "\n")
    return path


@click.command("fetch")
@click.argument("resource_id")
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True, help="Folder to write into.")
@server_option
@click.option("--all-images", is_flag=True, help="Images of every iteration that wrote them, not only the last.")
@click.option("--runs", "with_runs", is_flag=True, help="For an experiment: also fetch every run's job.")
def fetch_command(resource_id: str, out_dir: str, server: str, all_images: bool, with_runs: bool) -> None:
    """Download a job (records, images, checkpoint) or an experiment (its document, runs,
    results.csv, curves; --runs adds every run's job in a folder of its own)."""
    api, out = _client(server), Path(out_dir)
    try:
        if is_experiment_id(resource_id):
            out.mkdir(parents=True, exist_ok=True)
            _write_json(out / "experiment.json", api.experiment(resource_id))
            rows = api.runs(resource_id)
            _write_json(out / "runs.json", rows)
            _write_json(out / "curves.json", api.curves(resource_id))
            (out / "results.csv").write_text(api.results_csv(resource_id))
            count = 4
            for row in rows if with_runs else []:
                if row.get("job"):
                    count += len(fetch_job(api, row["job"], out / row["job"], all_images))
        else:
            count = len(fetch_job(api, resource_id, out, all_images))
    except ApiError as exc:
        raise _fail(exc) from None
    except ValueError as exc:
        raise click.ClickException(str(exc)) from None
    click.echo(f"{count} files in {out}")


# ------------------------------------------------------------------------------ ls


@click.command("ls")
@server_option
@click.option("--experiments", "only_experiments", is_flag=True, help="Only experiments.")
@click.option("--jobs", "only_jobs", is_flag=True, help="Only jobs.")
@click.option("--status", default=None, help="Only jobs with this status.")
@click.option("--limit", type=click.IntRange(1, 200), default=20, show_default=True, help="Rows per table.")
def ls_command(server: str, only_experiments: bool, only_jobs: bool, status: str | None, limit: int) -> None:
    """Jobs and experiments on the server, newest first."""
    from rich.console import Console
    from rich.table import Table

    api, console = _client(server), Console()
    try:
        if not only_experiments:
            table = Table(title="jobs")
            for column in ("id", "status", "method", "scene", "iterations", "loss", "name"):
                table.add_column(column, no_wrap=column == "id", min_width=20 if column == "id" else None)
            for job in api.jobs(status=status, limit=limit):
                done = 0 if job.get("iteration") is None else job["iteration"] + 1
                table.add_row(job["id"], job["status"], job["method"], job["scene"], f"{done}/{job['iterations']}",
                              fmt((job.get("metrics") or {}).get("loss")), (job.get("name") or "")[:50])
            console.print(table)
        if not only_jobs:
            table = Table(title="experiments")
            for column in ("id", "status", "runs", "by status", "varied", "name"):
                table.add_column(column, no_wrap=column == "id", min_width=21 if column == "id" else None)
            for experiment in api.experiments(limit=limit):
                counts = ", ".join(f"{k} {v}" for k, v in sorted(experiment["counts"].items()))
                table.add_row(experiment["id"], experiment["status"], str(experiment["runs"]), counts,
                              ", ".join(experiment["varied"]), (experiment.get("name") or "")[:50])
            console.print(table)
    except ApiError as exc:
        raise _fail(exc) from None
    except OSError as exc:
        raise click.ClickException(f"cannot reach {server}: {exc}") from None

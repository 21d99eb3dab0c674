"""``ndrf experiment SPEC.json --out DIR`` and ``ndrf compare JOB.json``: experiments in-process.

The embedded default, as ``ndrf serve`` without Redis runs it: the store is DIR, ``--jobs N``
worker threads each run one job at a time in its own sandboxed child process (N local processes),
and the experiment scheduler admits runs N at a time. The same spec file posts to a server
(``ndrf submit SPEC.json --server URL``). A local ``{"path": ...}`` scene is packed into an upload
first. Ctrl-C cancels the experiment (finished runs and the artifacts of the others are kept).
"""

from __future__ import annotations

import json
import logging
import signal
import time
from pathlib import Path

import click

from cli.experiment_report import accuracy_svg, aggregates_table, runs_table
from schemas.methods import methods_for

log = logging.getLogger(__name__)


def read_json(path: str | Path) -> dict:
    try:
        document = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise click.ClickException(f"{path}: {exc}") from None
    if not isinstance(document, dict):
        raise click.ClickException(f"{path}: expected a JSON object")
    return document


def parse_spec(document: dict, base_dir: Path):
    """An :class:`ExperimentSpec` from a spec file's JSON (its scene packed), or a ClickException
    listing every offending field."""
    from pydantic import ValidationError

    from client.scenes import SceneError, pack_scene
    from schemas.experiments import ExperimentSpec
    from schemas.validation import describe

    try:
        document = pack_scene(document, base_dir)
    except SceneError as exc:
        raise click.ClickException(str(exc)) from None
    try:
        return ExperimentSpec.model_validate(document)
    except ValidationError as exc:
        lines = "\n".join(f"  {field}: {msg}" for field, msg in describe(exc))
        raise click.ClickException(f"invalid experiment\n{lines}") from None


def _progress(console, total: int):
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

    return Progress(TextColumn("[bold]runs"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(),
                    TextColumn("{task.description}"), console=console)


def _running_text(runtime, record) -> str:
    """'3 queued · #2 it 14/60 · #5 warm-up' from the running runs' job records."""
    parts, queued = [], 0
    for run in record.runs:
        if run.status in ("queued", "admitting"):
            queued += 1
        elif run.status == "running" and run.job:
            job = runtime.service.states.get(run.job)
            done = 0 if job.iteration is None else job.iteration + 1
            parts.append(f"#{run.index} it {done}/{job.iterations}" if done else f"#{run.index} starting")
    pending = sum(run.status == "pending" for run in record.runs)
    head = [f"{pending} pending"] if pending else []
    head += [f"{queued} queued"] if queued else []
    return " · ".join(head + parts)


def run_experiment(spec, out: Path, jobs: int, quiet: bool = False) -> tuple[dict, list[dict], dict]:
    """Run ``spec`` to its end in the store ``out`` with ``jobs`` local processes; returns the
    experiment, its rows and its curves (as the API's JSON) and writes results.csv beside them."""
    from rich.console import Console

    from services.experiments.expand import InvalidExperiment
    from services.experiments.results import results_csv
    from services.jobs.preflight import preflight
    from services.runtime import build_runtime
    from services.settings import Settings
    from worker.main import make_worker

    console = Console(stderr=True)
    settings = Settings(store=str(out), redis_url=None, embedded_workers=jobs)
    runtime = build_runtime(settings)
    service = runtime.experiments
    try:
        if not quiet:
            console.print(f"checking {spec.name or 'the experiment'}: every run, the scene in a sandbox")
        try:
            record = service.create(spec, preflight=preflight, max_concurrent=jobs)
        except InvalidExperiment as exc:
            raise click.ClickException(f"invalid experiment: {exc.field}: {exc.message}") from None
        runtime.start_embedded_workers(make_worker)
        runtime.start_experiment_scheduler(interval=0.2)
        interrupted: list[bool] = []
        previous = signal.signal(signal.SIGINT, lambda *_: interrupted.append(True))
        try:
            record = _follow(runtime, record, console, quiet, interrupted)
        finally:
            signal.signal(signal.SIGINT, previous)
        rows = service.rows(record)
        (out / "results.csv").write_text(results_csv(rows))
        public = service.public(record).model_dump(mode="json")
        curves = service.curves(record).model_dump(mode="json")
        (out / f"experiment-{record.id}.json").write_text(json.dumps(public, indent=1) + "\n")
        (out / f"curves-{record.id}.json").write_text(json.dumps(curves) + "\n")
        return public, [r.model_dump(mode="json") for r in rows], curves
    finally:
        runtime.stop(timeout=90)


def _follow(runtime, record, console, quiet: bool, interrupted: list[bool]):
    service = runtime.experiments
    total = len(record.runs)
    canceled = False
    with _progress(console, total) if not quiet else _Silent() as progress:
        task = progress.add_task("", total=total)
        while True:
            record = service.states.get(record.id)
            finished = sum(run.status in ("succeeded", "failed", "canceled") for run in record.runs)
            progress.update(task, completed=finished, description=_running_text(runtime, record))
            if record.status.finished:
                return record
            if interrupted and not canceled:
                console.print("interrupted: canceling the experiment (finished runs are kept)")
                service.cancel(record.id)
                canceled = True
            time.sleep(0.5)


class _Silent:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def add_task(self, *args, **kwargs):
        return 0

    def update(self, *args, **kwargs):
        pass


def _jobs_option(function):
    return click.option("--jobs", "-j", type=click.IntRange(1, 16), default=1, show_default=True,
                        help="Runs at once, each in its own local process.")(function)


@click.command("experiment")
@click.argument("spec_path", type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), required=True,
              help="Store folder: one folder per run's job, results.csv, experiment-<id>.json.")
@_jobs_option
@click.option("--quiet", is_flag=True, help="No progress bar.")
def experiment_command(spec_path: str, out_dir: str, jobs: int, quiet: bool) -> None:
    """Run an experiment (a sweep over a job's fields) in-process: a progress bar over the runs,
    then the results table. The same file posts to a server: ndrf submit SPEC.json --server URL."""
    from rich.console import Console

    spec = parse_spec(read_json(spec_path), Path(spec_path).resolve().parent)
    out = Path(out_dir)
    started = time.monotonic()
    public, rows, _ = run_experiment(spec, out, jobs, quiet)
    console = Console()
    console.print(runs_table(public, rows))
    if len(rows) > len(public.get("aggregates") or []):
        console.print(aggregates_table(public))
    console.print(f"{public['status']} in {time.monotonic() - started:.0f} s wall; results in {out / 'results.csv'}")
    if public["status"] != "succeeded":
        raise SystemExit(1)


def compare_spec(job: dict, seeds: list[int], target_error: float | None) -> dict:
    name = job.get("name") or "job"
    methods = methods_for([p.get("key", "") for p in job.get("parameters") or [] if isinstance(p, dict)])
    spec: dict[str, object] = {"name": f"compare: {name}"[:200], "base": job, "grid": {"method": [m.value for m in methods]},
            "seeds": seeds, "objective": {"metric": "time_to_error" if target_error else "parameter_error"}}
    if target_error is not None:
        spec["target_error"] = target_error
    return spec


@click.command("compare")
@click.argument("job_path", type=click.Path(exists=True, dir_okay=False))
@click.option("--out", "out_dir", type=click.Path(file_okay=False), default=None,
              help="Store folder (default runs/compare-<job file name>).")
@_jobs_option
@click.option("--seeds", default="0,1,2", show_default=True, help="Comma-separated seeds.")
@click.option("--target-error", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Parameter error whose time to reach is compared (default 0.05).")
@click.option("--server", default=None, envvar="NDRF_SERVER",
              help="Run on this server instead (key from NDRF_API_KEY).")
@click.option("--quiet", is_flag=True, help="No progress bar.")
def compare_command(job_path: str, out_dir: str | None, jobs: int, seeds: str, target_error: float | None,
                    server: str | None, quiet: bool) -> None:
    """Which method for this scene, at what cost: the job with each gradient method that can run it
    (the five for materials and lights, the two projective ones for a pose) and several seeds,
    compared by accuracy against time (table, and OUT/compare.svg)."""
    from rich.console import Console

    try:
        seed_list = [int(s) for s in seeds.split(",") if s.strip()]
    except ValueError:
        raise click.ClickException(f"--seeds: expected integers separated by commas, got {seeds!r}") from None
    document = compare_spec(read_json(job_path), seed_list, target_error)
    out = Path(out_dir or f"runs/compare-{Path(job_path).stem}")
    out.mkdir(parents=True, exist_ok=True)
    started = time.monotonic()
    if server:
        from cli.remote import run_remote

        public, rows, curves = run_remote(server, document, Path(job_path).resolve().parent, quiet)
    else:
        spec = parse_spec(document, Path(job_path).resolve().parent)
        public, rows, curves = run_experiment(spec, out, jobs, quiet)
    wall = time.monotonic() - started
    console = Console()
    console.print(aggregates_table(public))
    over = f"mean over {len(seed_list)} seeds" if len(seed_list) > 1 else f"seed {seed_list[0]}"
    svg = accuracy_svg(curves["configurations"], f"{public.get('name')}: accuracy against time ({over})",
                       out / "compare.svg")
    console.print(f"{public['status']}: {len(rows)} runs in {wall:.0f} s wall ({jobs} at once); plot {svg}")

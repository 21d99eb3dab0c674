"""An experiment's warm start (``warm_start: "first_run"``) against the same experiment run cold:
``seeds x learning rates`` runs of one job through the experiment path (the embedded default, as
``ndrf experiment`` runs it: the scheduler, one worker, each run a sandboxed child process), once
with every run cold and once with run 0 cold and the other runs warm-started from it.

Per run, from the experiment's own rows (:mod:`services.experiments.results`): compute seconds
to the first iteration whose largest parameter error is at most ``--target-error``
(``time_to_error``: training, warm-up or the warm start's top-up, gradients, steps), the final
largest parameter error, compute seconds and wall seconds of the run (scene loading and the
child's start included), and the top-up steps. Per experiment: wall seconds from creation to its
end. Run 0 of the warm experiment is a cold run like any: the warm start pays it once.

    python -m bench.warm_start_experiment [--job examples/hidden-object.json] [--seeds 0,1]
        [--learning-rates 0.08,0.04,0.16] [--iterations N]
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
import tempfile
import time
from pathlib import Path

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent


def run_to_end(spec, store: Path, jobs: int = 1, on_rows=None) -> tuple[dict, list[dict]]:
    """``spec`` run to its end in the embedded default (as ``ndrf experiment`` runs it: the store
    is ``store``, ``jobs`` worker threads each run one job at a time in a sandboxed child, the
    scheduler admits the runs); the experiment and its rows as the API gives them."""
    from services.jobs.preflight import preflight
    from services.runtime import build_runtime
    from services.settings import Settings
    from worker.main import make_worker

    runtime = build_runtime(Settings(store=str(store), redis_url=None, embedded_workers=jobs))
    try:
        record = runtime.experiments.create(spec, preflight=preflight, max_concurrent=jobs)
        runtime.start_embedded_workers(make_worker)
        runtime.start_experiment_scheduler(interval=0.2)
        done = 0
        while not (record := runtime.experiments.states.get(record.id)).status.finished:
            finished = sum(run.status in ("succeeded", "failed", "canceled") for run in record.runs)
            if on_rows is not None and finished > done:   # the rows so far (a run cut short keeps them)
                done = finished
                on_rows([row.model_dump(mode="json") for row in runtime.experiments.rows(record)])
            time.sleep(0.5)
        rows = [row.model_dump(mode="json") for row in runtime.experiments.rows(record)]
        return runtime.experiments.public(record).model_dump(mode="json"), rows
    finally:
        runtime.stop(timeout=90)


KEEP = ("index", "seed", "varied", "time_to_error", "final_parameter_error", "seconds", "wall_seconds", "warm_start")


def experiment(job: dict, seeds: list[int], rates: list[float], target_error: float, warm: bool,
               on_rows=None) -> dict:
    """One experiment to its end in a scratch store; its rows and wall seconds."""
    from schemas.experiments import ExperimentSpec

    spec = ExperimentSpec.model_validate({
        "name": f"bench warm start ({'warm' if warm else 'cold'})", "base": job, "seeds": seeds,
        "grid": {"learning_rate": rates}, "max_concurrent": 1, "target_error": target_error,
        "objective": {"metric": "time_to_error"}, "warm_start": "first_run" if warm else None})
    folder = Path(tempfile.mkdtemp(prefix="bench-warm-experiment-"))
    try:
        started = time.perf_counter()
        public, rows = run_to_end(spec, folder, on_rows=on_rows)
        seconds = time.perf_counter() - started
    finally:
        shutil.rmtree(folder, ignore_errors=True)
    if public["status"] != "succeeded":
        raise RuntimeError(f"the {'warm' if warm else 'cold'} experiment {public['status']}: "
                           f"{[r.get('error') for r in rows]}")
    return {"wall_seconds": seconds, "runs": [{k: row.get(k) for k in KEEP} for row in rows]}


def table(result: dict, target_error: float) -> str:
    def cell(value):
        return "not reached" if value is None else value

    cold, warm = result.get("cold"), result.get("warm")
    by_index = [{r["index"]: r for r in (e or {"runs": []})["runs"]} for e in (cold, warm)]
    lines = []
    for index in sorted(set(by_index[0]) | set(by_index[1])):
        c, w = by_index[0].get(index, {}), by_index[1].get(index, {})
        run = c or w
        reused = w.get("warm_start") or {}
        lines.append([index, run["seed"], run["varied"].get("learning_rate"),
                      cell(c.get("time_to_error")) if c else "", cell(w.get("time_to_error")) if w else "",
                      c.get("final_parameter_error"), w.get("final_parameter_error"),
                      c.get("seconds"), w.get("seconds"), c.get("wall_seconds"), w.get("wall_seconds"),
                      reused.get("top_up_steps", "cold (source)" if w else "")])
    total = ["experiment", "", "", "", "", "", "",
             sum(r["seconds"] or 0 for r in cold["runs"]) if cold else "",
             sum(r["seconds"] or 0 for r in warm["runs"]) if warm else "",
             cold["wall_seconds"] if cold else "", warm["wall_seconds"] if warm else "", ""]
    return markdown_table(["run", "seed", "learning rate", f"s to {target_error} cold", f"s to {target_error} warm",
                           "final error cold", "final error warm", "compute s cold", "compute s warm",
                           "wall s cold", "wall s warm", "top-up steps"], lines + [total])


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.warm_start_experiment", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", type=Path, default=ROOT / "examples" / "hidden-object.json")
    parser.add_argument("--seeds", default="0,1")
    parser.add_argument("--learning-rates", default="0.08,0.04,0.16",
                        help="the first is run 0's (the base job's own rate by default)")
    parser.add_argument("--iterations", type=int, default=None, help="override the job's iterations")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    job = json.loads(args.job.read_text())
    if args.iterations is not None:
        job["iterations"] = args.iterations
    job["images_every"] = job["iterations"]
    seeds, rates = [int(s) for s in args.seeds.split(",")], [float(r) for r in args.learning_rates.split(",")]
    out = args.out or ROOT / "bench" / "results" / f"warm_start_experiment-{args.job.stem}.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    result: dict = {"machine": machine(), "job": str(args.job), "target_error": args.target_error,
                    "iterations": job["iterations"], "note": "a shared 2-core machine (other work ran beside it)"}
    def write() -> None:
        out.write_text(json.dumps(result, indent=1))
        write_markdown(out, "bench.warm_start_experiment", argv,
                       f"{result['note']}; {job['iterations']} iterations.\n\n" + table(result, args.target_error))

    for name, warm in (("warm", True), ("cold", False)):   # warm first: a failure shows early

        def partial(rows: list[dict], name=name) -> None:
            result[name] = {"wall_seconds": None, "partial": True,
                            "runs": [{k: row.get(k) for k in KEEP} for row in rows if row["status"] == "succeeded"]}
            write()

        result[name] = experiment(job, seeds, rates, args.target_error, warm, on_rows=partial)
        log.info("%s experiment: %.0f s", name, result[name]["wall_seconds"])
        write()
    log.info("\n%s", table(result, args.target_error))


if __name__ == "__main__":
    main()

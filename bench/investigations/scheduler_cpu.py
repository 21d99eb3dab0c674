"""CPU of the experiment scheduler with many active experiments (issue 38: 60 experiments of 200
runs took 20% of a core, every experiment re-read every 0.5 s): 60 experiments of ``--runs`` runs
(``max_concurrent`` 1) in a folder store (the embedded mode), a job waiting in the queue (a busy
service: nothing is admitted), then the CPU seconds of 20 ticks, i.e. 10 s at the 0.5 s interval,
after a first tick.

    python -m bench.investigations.scheduler_cpu [--runs 200] [--experiments 60]
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time

from harness.cluster import small_job
from schemas.experiments import ExperimentSpec
from schemas.job import JobSpec
from services.experiments.scheduler import Scheduler
from services.experiments.service import ExperimentService
from services.jobs.service import Caller, JobService
from services.queue.local import LocalEventBus, LocalJobQueue
from services.settings import Limits
from services.store.local import FolderStore

log = logging.getLogger("bench.investigations.scheduler_cpu")


def measure(runs: int, experiments_count: int, ticks: int = 20) -> float:
    with tempfile.TemporaryDirectory() as tmp:
        store, queue = FolderStore(tmp), LocalJobQueue()
        jobs = JobService(store, queue, LocalEventBus())
        experiments = ExperimentService(jobs, Limits(experiments_per_key=100))
        for i in range(experiments_count):
            spec = ExperimentSpec.model_validate({"base": small_job("direct", iterations=2),
                                                  "seeds": list(range(runs)), "max_concurrent": 1})
            experiments.create(spec, Caller(f"key{i % 5}"))
        jobs.submit(JobSpec.model_validate(small_job("direct", iterations=2)), Caller("bob"))
        scheduler = Scheduler(experiments, queue)
        scheduler.tick()
        cpu = time.process_time()
        for _ in range(ticks):
            scheduler.tick()
        return time.process_time() - cpu


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=200)
    parser.add_argument("--experiments", type=int, default=60)
    args = parser.parse_args()
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    cpu = measure(args.runs, args.experiments)
    log.info("%d experiments of %d runs: 20 ticks (10 s at 0.5 s) took %.2f CPU s (%.1f%% of a core)",
             args.experiments, args.runs, cpu, 10 * cpu)


if __name__ == "__main__":
    main()

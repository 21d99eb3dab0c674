"""Chaos benchmark: N jobs on W workers in Redis mode while things break (the harness:
:mod:`harness.chaos`, which says what breaks and what is reported).

    python -m bench.chaos                      # 10 jobs, 3 workers, a SIGKILL every 60 s, one Redis restart,
                                               # one full disk
    python -m bench.chaos --quick              # 4 jobs, 2 workers, a kill every 20 s (a few minutes)

Writes ``bench/results/chaos.json`` and ``chaos.md``.
"""

from __future__ import annotations

import argparse
import json
import logging
import shutil
from pathlib import Path

from harness.chaos import ChaosConfig, markdown, run

log = logging.getLogger("bench.chaos")


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="4 jobs, 2 workers, a kill every 20 s, lease 5 s.")
    parser.add_argument("--jobs", type=int)
    parser.add_argument("--workers", type=int)
    parser.add_argument("--iterations", type=int)
    parser.add_argument("--kill-every", type=float)
    parser.add_argument("--lease", type=float)
    parser.add_argument("--redis-restart-after", type=float)
    parser.add_argument("--disk-full-after", type=float)
    parser.add_argument("--no-disk-full", action="store_true")
    parser.add_argument("--out", default="bench/results/chaos", help="Writes OUT.json and OUT.md.")
    parser.add_argument("--keep", action="store_true", help="Keep the run's folder (store, logs).")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    config = ChaosConfig(jobs=4, workers=2, iterations=30, kill_every=20, lease_seconds=5, redis_restart_after=30,
                         disk_full_after=50) if args.quick else ChaosConfig()
    for name, value in (("jobs", args.jobs), ("workers", args.workers), ("iterations", args.iterations),
                        ("kill_every", args.kill_every), ("lease_seconds", args.lease),
                        ("redis_restart_after", args.redis_restart_after), ("disk_full_after", args.disk_full_after)):
        if value is not None:
            setattr(config, name, value)
    if args.no_disk_full:
        config.disk_full_after = None
    report = run(config)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(report, indent=2) + "\n")
    out.with_suffix(".md").write_text(markdown(report))
    log.info("%s", markdown(report))
    if not args.keep:
        shutil.rmtree(report["folder"], ignore_errors=True)


if __name__ == "__main__":
    main()

"""Seconds per ``prb`` iteration: the product's loop against the hand-written Mitsuba loop, at equal
settings.

``python -m bench.prb_iteration [--job examples/room-open-8.json] [--rounds 3] [--iterations 60]``

Both run the job from its initial values for ``--iterations`` iterations of one view, 1 spp and
Russian roulette from depth 5 with Adam: the loop is :func:`bench.mitsuba_loop.run_loop` (Mitsuba's
tutorial loop: ``mi.render``, ``dr.backward``, ``mi.ad.Adam``, clipping, the parameter error read
back), the product is the job through ``run_local`` with ``"method": "prb", "optimizer": "adam"``:
its records, events, checkpoints and images (on their default 5% budget) included. The two
alternate ``--rounds`` times in one process, after one untimed run of each (kernel compilation),
so that a busy machine slows both; reported: the median seconds per iteration of each round and
their ratio. A third column is the same loop with each view's render, loss and backward in
``dr.freeze`` (``LoopSetting(freeze=True)``, not the tutorial's): what a user who freezes their
own loop gets, against the product, which freezes by default (``render.freeze``).

Each side runs with its own scene the only one alive (:func:`bench.common.loop_rows`): Dr.Jit
traces every live instance at a virtual call, and a second scene alive made the product's
iteration about 20% slower in the bench's earlier form, which kept the loop's scene alive.
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from bench.common import loop_rows, machine, markdown_table, write_markdown
from bench.mitsuba_loop import LoopSetting, run_loop
from bench.regime import default_job, merge, run_product

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
ADAM = {"method": "prb", "optimizer": "adam", "views_per_iteration": 1}


def run(job: dict, rounds: int, iterations: int) -> list[dict]:
    base = merge(default_job(job), ADAM)
    settings = {"loop": LoopSetting(spp=1, rr_depth=5, views=1),
                "loop_frozen": LoopSetting(spp=1, rr_depth=5, views=1, freeze=True)}
    for setting in settings.values():
        loop_rows(base, lambda prepared, s=setting: run_loop(prepared, s, target_error=0.0, iterations=3))
    run_product(merge(base, {"targets": {"synthetic": {"spp": 1}}}), 0.0, iterations=3)
    rows = []
    for r in range(rounds):
        row: dict = {"round": r}
        for name, setting in settings.items():
            loop, _ = loop_rows(base, lambda prepared, s=setting, r=r: run_loop(prepared, s, target_error=0.0,
                                                                             iterations=iterations, seed=r))
            row[name] = loop["seconds_per_iteration"]
        row["product"] = run_product(dict(base, seed=r), 0.0, iterations=iterations)["seconds_per_iteration"]
        rows.append(row)
        log.info("round %d: %s", r, rows[-1])
    return rows


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.prb_iteration", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", type=Path, default=ROOT / "examples" / "room-open-8.json")
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=60)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "prb_iteration.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    rows = run(json.loads(args.job.read_text()), args.rounds, args.iterations)
    ratios = [r["product"] / r["loop"] for r in rows]
    frozen = [r["product"] / r["loop_frozen"] for r in rows]
    args.out.write_text(json.dumps({"machine": machine(), "job": str(args.job), "rows": rows,
                                    "median_ratio": float(np.median(ratios)),
                                    "median_ratio_to_frozen_loop": float(np.median(frozen))}, indent=1))
    lines = [[r["round"], f"{r['loop']:.4f}", f"{r['loop_frozen']:.4f}", f"{r['product']:.4f}",
              f"{r['product'] / r['loop']:.2f}x", f"{r['product'] / r['loop_frozen']:.2f}x"] for r in rows]
    lines.append(["median", "", "", "", f"{np.median(ratios):.2f}x", f"{np.median(frozen):.2f}x"])
    text = markdown_table(["round", "loop s / iteration", "loop, frozen", "product s / iteration", "product / loop",
                           "product / frozen loop"], lines)
    write_markdown(args.out, "bench.prb_iteration", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

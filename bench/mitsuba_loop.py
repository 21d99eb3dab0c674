"""The loop a user writes instead of the product: Mitsuba's tutorial optimization loop with ``prb``.

``python -m bench.mitsuba_loop --job examples/room-open-8.json [--spp 1,4] [--rr 5,off] [--views 1,2,4,all]``

Per iteration, as in Mitsuba's "gradient-based optimization" tutorial: render each view of the
iteration with ``mi.render(scene, params, integrator=prb, spp=..., seed=...)``, add
``dr.mean(dr.square(image - target))`` to the loss, ``dr.backward(loss)``, ``mi.ad.Adam`` (β =
0.8, 0.99) steps, the values are clipped to the job's bounds, ``params.update(opt)``, and the
parameter error is read back (the tutorial prints it every iteration). The learning rate decays
geometrically from the job's ``learning_rate`` to ``final_learning_rate_ratio`` of it. With ``v``
random views of ``S`` per iteration the loop runs ``iterations · S / v`` iterations, so every
setting renders the same number of views.

Everything but the loop comes from the product, so both see the same problem: the scene, the
initial values, the bounds and the target images (``services.solver.optimize.setup.prepare``).
Scene loading and target rendering are outside the clock; each setting runs once untimed for two
iterations first (kernel compilation), then from the initial values on the clock. A setting is
the best loop of the grid when it first reaches ``--target-error`` soonest.

``LoopSetting(freeze=True)`` is not the tutorial's loop: it runs each view's render, loss and
``dr.backward`` in ``dr.freeze``, as the product does (``bench.prb_iteration`` reports it beside the
tutorial's, for what a user who freezes their own loop would see).

Grid: ``spp`` in {1, 4}, Russian roulette from depth 5 (Mitsuba's default) or off (paths then end
at depth 64: unbounded paths need roulette to end), views per iteration in {1, 2, 4, all} (a
single-view job has one).
"""

from __future__ import annotations

import argparse
import json
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parent.parent
#: Render seeds of the loop's run ``seed`` start at ``seed x RUN_SEEDS`` (its views, drawn with ``seed``, too).
RUN_SEEDS = 1_000_000
#: Path depth of the loop with Russian roulette off (the paths must end somewhere).
DEPTH_WITHOUT_ROULETTE = 64


@dataclass(frozen=True)
class LoopSetting:
    spp: int
    rr_depth: int | None  # None: Russian roulette off
    views: int | None     # None: every view
    freeze: bool = False  # the render, loss and backward of a view in dr.freeze (not the tutorial's)

    @property
    def label(self) -> str:
        rr = "off" if self.rr_depth is None else str(self.rr_depth)
        frozen = " frozen" if self.freeze else ""
        return f"loop spp={self.spp} rr={rr} views={'all' if self.views is None else self.views}{frozen}"


def _view_gradient(scene, params, target, seed, *, sensor: int, spp: int, integrator):
    """A frozen loop's view: the tutorial's render, loss and ``dr.backward``. The gradients are read
    after the call: a frozen call is an isolated gradient scope, and a 3-channel texture's gradient
    reaches its ``data`` only when the call returns (``services.solver.estimators.methods.prb``)."""
    import drjit as dr
    import mitsuba as mi

    image = mi.render(scene, params, sensor=sensor, integrator=integrator, spp=spp, seed=seed)
    dr.backward(dr.mean(dr.square(image[..., :3] - target)))


def grid(spps: list[int], rrs: list[int | None], views: list[int | None]) -> list[LoopSetting]:
    return [LoopSetting(s, r, v) for s in spps for r in rrs for v in views]


def run_loop(prepared, setting: LoopSetting, *, target_error: float, budget: float | None = None,
             iterations: int | None = None, seed: int = 0, truth: np.ndarray | None = None) -> dict:
    """One run of the tutorial loop on a prepared job; returns its error curve (seconds since the
    loop started; per iteration the max and the RMS of ``|p - truth|`` over every scalar, ``truth``
    ``(P,)`` by default the job's synthetic target values) and the time it first reached
    ``target_error`` (max)."""
    import drjit as dr
    import mitsuba as mi

    spec, problem = prepared.spec, prepared.problem
    scene, params = problem.scene.scene, problem.scene.params
    keys = problem.parameters.keys
    sensors = sorted(prepared.targets)
    per_view = setting.views or len(sensors)
    total = iterations or max(1, spec.iterations * len(sensors) // per_view)
    truth = prepared.target_values if truth is None else truth
    if truth is None:
        raise ValueError("the loop's error needs the true values: a synthetic target, or truth=")
    lower, upper = prepared.lower, prepared.upper
    offsets = np.cumsum([0] + [info.size for info in problem.parameters.infos])
    depth = (-1, setting.rr_depth) if setting.rr_depth is not None else (DEPTH_WITHOUT_ROULETTE, DEPTH_WITHOUT_ROULETTE + 1)
    integrator = mi.load_dict({"type": "prb", "max_depth": depth[0], "rr_depth": depth[1]})
    targets = {s: mi.TensorXf(np.asarray(prepared.targets[s], np.float32)) for s in sensors}
    problem.parameters.assign(prepared.init)
    opt = mi.ad.Adam(lr=spec.learning_rate, beta_1=0.8, beta_2=0.99)
    for key in keys:
        opt[key] = params[key]
    params.update(opt)
    frozen = dr.freeze(_view_gradient, warn_after=64) if setting.freeze else None
    rng = np.random.default_rng(seed)
    curve, reached = [], None
    start = time.perf_counter()
    for it in range(total):
        opt.set_learning_rate(spec.learning_rate * spec.final_learning_rate_ratio ** (it / max(total - 1, 1)))
        views = sensors if setting.views is None else rng.choice(sensors, setting.views, replace=False)
        for sensor in views:
            if frozen is None:
                image = mi.render(scene, params, sensor=int(sensor), integrator=integrator, spp=setting.spp,
                                  seed=it * len(sensors) + int(sensor) + RUN_SEEDS * seed)
                dr.backward(dr.mean(dr.square(image[..., :3] - targets[int(sensor)])))
                continue
            frozen(scene, params, targets[int(sensor)], dr.opaque(mi.UInt32, it * len(sensors) + int(sensor)
                                                                   + RUN_SEEDS * seed),
                   sensor=int(sensor), spp=setting.spp, integrator=integrator)
        opt.step()
        for i, key in enumerate(keys):
            lo, hi = float(lower[offsets[i]]), float(upper[offsets[i]])
            opt[key] = dr.clip(opt[key], lo, hi if np.isfinite(hi) else 1e30)
        params.update(opt)
        values = np.concatenate([np.asarray(params[key], np.float64).reshape(-1) for key in keys])
        error = float(np.max(np.abs(values - truth)))
        seconds = time.perf_counter() - start
        curve.append({"iteration": it, "seconds": seconds, "error": error,
                      "rmse": float(np.sqrt(np.mean((values - truth) ** 2)))})
        if reached is None and error < target_error:
            reached = curve[-1]
        if budget is not None and seconds > budget:
            break
    problem.parameters.assign(prepared.init)
    return {"setting": setting.label, "curve": curve, "reached": reached, "final_error": curve[-1]["error"],
            "iterations": len(curve), "seconds_per_iteration": float(np.median(np.diff([0.0] + [c["seconds"]
                                                                                       for c in curve])))}


def run_grid(prepared, settings: list[LoopSetting], *, target_error: float, budget: float | None) -> dict[str, dict]:
    """Every setting, each compiled untimed first; results by label."""
    results = {}
    for setting in settings:
        run_loop(prepared, setting, target_error=target_error, iterations=2)
        log.info("mitsuba loop: %s", setting.label)
        results[setting.label] = run_loop(prepared, setting, target_error=target_error, budget=budget)
    return results


def best(results: dict[str, dict]) -> tuple[str, dict] | None:
    """The setting that first reached the target error soonest (None if none did)."""
    done = [(label, r) for label, r in results.items() if r["reached"] is not None]
    return min(done, key=lambda item: item[1]["reached"]["seconds"]) if done else None


def table(results: dict[str, dict], target_error: float) -> str:
    rows = []
    for label, r in results.items():
        reached = r["reached"]
        rows.append([label, f"{r['seconds_per_iteration']:.3f}",
                     f"{reached['seconds']:.2f} (iteration {reached['iteration']})" if reached else "not reached",
                     f"{r['final_error']:.4f} after {r['iterations']}"])
    return markdown_table(["setting", "s / iteration", f"seconds to max error < {target_error}", "final max error"],
                          rows)


def _values(text: str, parse) -> list:
    return [parse(v.strip()) for v in text.split(",") if v.strip()]


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.mitsuba_loop", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", type=Path, required=True, help="a job file with synthetic targets")
    parser.add_argument("--spp", default="1,4")
    parser.add_argument("--rr", default="5,off", help="Russian roulette depths; 'off' for none")
    parser.add_argument("--views", default="1,2,4,all")
    parser.add_argument("--target-error", type=float, default=0.02)
    parser.add_argument("--budget", type=float, default=60.0, help="stop a setting after this many seconds")
    parser.add_argument("--out", type=Path, default=None)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    from schemas.job import JobSpec
    from services.solver.optimize.setup import prepare

    prepared, _ = prepare(JobSpec.model_validate(json.loads(args.job.read_text())))
    settings = grid(_values(args.spp, int), _values(args.rr, lambda v: None if v == "off" else int(v)),
                    _values(args.views, lambda v: None if v == "all" else int(v)))
    results = run_grid(prepared, settings, target_error=args.target_error, budget=args.budget)
    out = args.out or ROOT / "bench" / "results" / f"mitsuba-loop-{args.job.stem}.json"
    out.write_text(json.dumps({"machine": machine(), "job": str(args.job), "results": results}, indent=1))
    text = table(results, args.target_error)
    write_markdown(out, "bench.mitsuba_loop", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

"""Does checking ``ndrf-lhs``'s ``dz/dp`` against ``prb``'s make its answer's error bar honest, and
which test of the checks' mean does it need? (issue 44)

    python -m bench.investigations.bias_check --jobs bright-room,room-closed-8 --seeds 0,1,2 --budgets 0.5

Each example runs as its file is written (only ``seed`` and ``iterations`` change), with
``ndrf-lhs`` among the checked methods (``prb``'s unbiased ``dz/dp`` of the same views every
:data:`~services.solver.optimize.rules.bias.BIAS_EVERY` iterations, from samples of its own, so the run's
steps are those of an unchecked run). The answer at the end is then formed four ways from the same
run, and each one's error is set against its standard error:

* ``unchecked``: the checks dropped (what the product returns for ``ndrf-lhs`` today);
* ``chi2``: corrected where ``χ²`` of the checks' mean with their sample covariance passes its 95%
  quantile (the test before this investigation);
* ``t``: corrected where some scalar's ``t`` passes its Šidák-corrected quantile (a valid test
  at 5% with few checks);
* ``always``: always corrected (unbiased, with ``prb``'s noise in the correction): the product
  since this investigation;
* ``cover``: ``t``'s correction where it finds a bias; elsewhere the estimate stays and its error
  takes the bias the checks cannot rule out.

Results: ``bench/results/bias_check.json`` (each run's errors and standard errors per variant) and
a table by job, budget and variant.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from bench.common import chosen, machine, markdown_table, write_markdown

log = logging.getLogger("bench.investigations.bias_check")
ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "bench" / "results" / "bias_check.json"
JOBS = ("bright-room", "room-closed-8", "room-closed-deep", "hidden-object")
VARIANTS = ("unchecked", "chi2", "t", "always", "cover")


def _chi2_biased(differences: np.ndarray, level: float = 0.95) -> bool:
    """The test before this investigation: ``χ²`` of the checks' mean with their sample covariance
    (singular or nearly so with few checks: it passes on noise alone)."""
    from services.solver.optimize.significance import chi2_quantile

    mean = differences.mean(axis=0)
    spread = np.atleast_2d(np.cov(differences, rowvar=False)) / len(differences)
    scale = np.sqrt(np.clip(np.diag(spread), 1e-300, None))
    chi2 = float(mean / scale @ np.linalg.pinv(spread / np.outer(scale, scale)) @ (mean / scale))
    return chi2 > chi2_quantile(mean.size, level)


def t_quantile(q: float, dof: int) -> float:
    """The ``q`` quantile (``q`` in [0.5, 1)) of Student's ``t``: its density integrated by
    Simpson's rule, inverted by bisection (within 1e-6 of the tables)."""
    from math import lgamma

    norm = np.exp(lgamma((dof + 1) / 2) - lgamma(dof / 2)) / np.sqrt(dof * np.pi)

    def cdf(x: float) -> float:
        t = np.linspace(0.0, x, 4001)
        density = norm * (1 + t * t / dof) ** (-(dof + 1) / 2)
        return 0.5 + (t[1] - t[0]) / 3 * float(density[0] + density[-1] + 4 * density[1:-1:2].sum()
                                                 + 2 * density[2:-1:2].sum())

    lo, hi = 0.0, 1.0
    while cdf(hi) < q:
        lo, hi = hi, 2 * hi
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if cdf(mid) < q else (lo, mid)
    return (lo + hi) / 2


def _t_biased(differences: np.ndarray, level: float = 0.95) -> bool:
    """Some scalar's ``t = d̄ / (s / sqrt(n))`` beyond Student's quantile for ``n - 1`` degrees of
    freedom, Šidák-corrected for the ``P`` scalars (a valid 5% test with few checks)."""
    n, p = differences.shape
    spread, mean = differences.std(axis=0, ddof=1), differences.mean(axis=0)
    tested = spread > 0
    t = np.abs(mean[tested]) / (spread[tested] / np.sqrt(n))
    return bool(np.any(t > t_quantile(1 - (1 - level ** (1 / p)) / 2, n - 1)))


def _gated(test):
    """The product's correction (:meth:`NewtonAnswer._bias`), applied only where ``test`` passes;
    ``"cover"``: elsewhere the estimate stays and its covariance takes ``H⁻¹ d̄ d̄ᵀ H⁻¹``."""
    from services.solver.optimize.answer import MIN_CHECKS, NewtonAnswer

    correct = NewtonAnswer._bias

    def bias(self, start: int, h_inv: np.ndarray):
        differences = np.array([d for k, d in self.checks if k >= start])
        if len(differences) < MIN_CHECKS:
            return None
        if (_t_biased if test == "cover" else test)(differences):
            return correct(self, start, h_inv)
        if test != "cover":
            return None
        shift = h_inv @ differences.mean(axis=0)   # E d̄ d̄ᵀ = b bᵀ + Cov d̄
        return np.zeros_like(shift), np.outer(shift, shift)

    return bias


def variants(answer) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{variant: (estimate, standard error)}`` of one run's final answer."""
    import copy
    from unittest import mock

    from services.solver.optimize.answer import NewtonAnswer

    out = {}
    for name in VARIANTS:
        formed = copy.copy(answer)
        if name == "unchecked":
            formed.checks = []
        gate = {"chi2": _chi2_biased, "t": _t_biased, "cover": "cover"}.get(name)
        with mock.patch.object(NewtonAnswer, "_bias", _gated(gate)) if gate else contextlib.nullcontext():
            estimate = formed.estimate()
        out[name] = (estimate.values, estimate.standard_error)
    return out


def run(job: dict, seed: int, iterations: int) -> dict:
    """One checked run of ``job``; its answer formed every way of :data:`VARIANTS`."""
    from unittest import mock

    from schemas.job import JobSpec
    from schemas.methods import Method
    from services.jobs.local import run_local
    from services.solver.optimize import answer as module
    from services.solver.optimize.rules import bias as rule

    captured: list = []
    estimate = module.NewtonAnswer.estimate

    def capture(self):
        if not captured or captured[-1] is not self:
            captured.append(self)
        return estimate(self)

    checked = (*rule.BIASED_GRADIENTS, Method.NDRF_LHS)
    started = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp, mock.patch.object(rule, "BIASED_GRADIENTS", checked), \
            mock.patch.object(module.NewtonAnswer, "estimate", capture):
        summary = run_local(JobSpec.model_validate(dict(job, seed=seed, iterations=iterations)), Path(tmp) / "job")
    truth = np.asarray(summary["target_values"], float)
    formed = variants(captured[-1])
    state = captured[-1].state_dict()
    return {"seed": seed, "iterations": iterations, "ran": summary["iterations"], "stopped": summary["stopped"]["reason"],
            "checks": len(captured[-1].checks), "seconds": time.perf_counter() - started,
            "variants": {name: {"error": (values - truth).tolist(),
                                "standard_error": None if se is None else np.asarray(se).tolist()}
                         for name, (values, se) in formed.items()},
            "answer": _plain(state), "truth": truth.tolist(), "views": captured[-1].floor.views}


def _plain(value):
    """An answer's ``state_dict`` as JSON (arrays as lists), for forming it again offline
    (:func:`restored`)."""
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def restored(record: dict):
    """The final answer of a recorded run (its ``answer`` state), to form again offline."""
    from services.solver.optimize.answer import NewtonAnswer

    state = record["answer"]
    answer = NewtonAnswer(np.zeros(len(record["truth"])), np.ones(len(record["truth"])), record.get("views", 1))
    answer.load_state_dict(state)
    return answer


def judge(runs: list[dict], variant: str) -> dict:
    errors = [np.abs(r["variants"][variant]["error"]) for r in runs]
    ratios = np.concatenate([e / np.asarray(r["variants"][variant]["standard_error"]) for e, r in zip(errors, runs)
                             if r["variants"][variant]["standard_error"] is not None])
    return {"median_max_error": float(np.median([e.max() for e in errors])),
            "coverage": float(np.mean(ratios <= 2)), "median_ratio": float(np.median(ratios))}


def table(results: dict) -> str:
    rows = [[job, str(its), variant, f"{j['median_max_error']:.3g}", f"{100 * j['coverage']:.0f}%",
             f"{j['median_ratio']:.2f}", str(len(runs))]
            for job, by_budget in results["jobs"].items() for its, runs in by_budget.items()
            for variant in VARIANTS for j in [judge(runs, variant)]]
    return markdown_table(["job", "iterations", "answer", "median max error", "coverage of ±2 SE",
                           "median |error|/SE", "seeds"], rows)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--jobs", default="bright-room,room-closed-8")
    parser.add_argument("--seeds", default="0,1,2")
    parser.add_argument("--budgets", default="0.5", help="multiples of each example's iterations")
    parser.add_argument("--out", type=Path, default=OUT)
    parser.add_argument("--offline", action="store_true",
                        help="no runs: form the recorded runs' answers again (after a change to the variants; "
                             "needs a file written with --keep-answers)")
    parser.add_argument("--keep-answers", action="store_true",
                        help="keep each run's answer state in --out (hundreds of MB for room-closed-8's floor: "
                             "keep such a file out of bench/results)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    results = json.loads(args.out.read_text()) if args.out.exists() else {"machine": machine(), "jobs": {}}
    if args.offline:
        for runs in (runs for by_budget in results["jobs"].values() for runs in by_budget.values()):
            for record in runs:
                truth = np.asarray(record["truth"])
                record["variants"] = {name: {"error": (values - truth).tolist(),
                                             "standard_error": None if se is None else np.asarray(se).tolist()}
                                      for name, (values, se) in variants(restored(record)).items()}
        args.out.write_text(json.dumps(results, indent=1))
    for name in [] if args.offline else chosen(args.jobs, JOBS, parser, "job"):
        job = json.loads((ROOT / "examples" / f"{name}.json").read_text())
        for budget in (float(b) for b in args.budgets.split(",")):
            iterations = max(1, round(budget * job["iterations"]))
            runs = results["jobs"].setdefault(name, {}).setdefault(str(iterations), [])
            for seed in (int(s) for s in args.seeds.split(",")):
                if any(r["seed"] == seed for r in runs):
                    continue
                runs.append(run(job, seed, iterations))
                if not args.keep_answers:
                    runs[-1].pop("answer")
                log.info("%s seed %d, %d iterations: %s", name, seed, iterations,
                         {v: round(float(np.max(np.abs(runs[-1]["variants"][v]["error"]))), 4) for v in VARIANTS})
                args.out.write_text(json.dumps(results, indent=1))
    log.info("\n%s", table(results))
    write_markdown(args.out, "bench.investigations.bias_check", argv, table(results))


if __name__ == "__main__":
    main()

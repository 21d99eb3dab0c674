"""The default recipe through the loop on a multi-view scene: batches of views, the decisions it
takes on the way, and a resume that continues exactly where the run stopped (the optimizer's trust
radius, the stream of views, the batch size and the remembered Jacobians are all checkpointed)."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest


def _job(**extra) -> dict:
    from tests.support.jobs import small_room_job

    return small_room_job(**{"iterations": 12, "checkpoint_every": 2, "seed": 5, **extra})


def test_the_default_recipe_batches_views_and_resumes_exactly(mi, tmp_path):
    from tests.support.jobs import run_job as _run

    reference = _run(_job(), tmp_path / "uninterrupted")
    assert reference["status"] == "succeeded"
    records = [json.loads((tmp_path / "uninterrupted" / "iterations" / f"{k:06d}" / "record.json").read_text())
               for k in range(12)]
    views = [r["views"] for r in records]
    singles = list(itertools.takewhile(lambda v: len(v) == 1, views))   # one view per iteration, until it grows
    assert len(singles) >= 4 and len({v[0] for v in singles}) == len(singles)   # drawn without replacement
    assert all(len(set(v)) == len(v) for v in views) and max(len(v) for v in views) > 1
    plan = json.loads((tmp_path / "uninterrupted" / "plan.json").read_text())
    assert plan["recipe"]["optimizer"] == "levenberg-marquardt"
    assert np.max(np.abs(np.asarray(reference["estimate"]) - np.asarray(reference["target_values"]))) < \
        np.max(np.abs(np.asarray(reference["init"]) - np.asarray(reference["target_values"])))

    calls = {"n": 0}

    def stop_after_a_while():
        calls["n"] += 1
        return "interrupted" if calls["n"] > 7 else None   # polled once per iteration (no fields to train)

    out = tmp_path / "interrupted"
    assert _run(_job(), out, should_stop=stop_after_a_while)["status"] == "interrupted"
    resumed = _run(_job(), out, resume=True)
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in events if e["type"] == "resumed"][0] >= 4
    assert resumed["status"] == "succeeded"
    np.testing.assert_allclose(resumed["estimate"], reference["estimate"], rtol=1e-6, atol=1e-9)


def test_a_cancel_during_the_set_up_ends_it_there(mi, tmp_path):
    """A cancel asked while the job is being set up ends the run before the next set-up phase
    (#46: a big mesh's set-up is cancelable, not only killed at the end of the grace period): no
    synthetic target is rendered and no plan is written. Failed before the set-up's phases
    polled the host (the first poll came after the targets, the plan already written)."""
    from tests.support.jobs import run_job, small_job

    summary = run_job(small_job(), tmp_path, should_stop=lambda: "canceled")
    assert summary["status"] == "canceled" and summary["iterations"] == 0
    assert not (tmp_path / "plan.json").exists()
    assert not list(tmp_path.glob("targets/*"))


@pytest.mark.slow
def test_a_biased_method_is_checked_against_prb_and_resumes_exactly(mi, tmp_path):
    """ndrf-rhs under Levenberg-Marquardt: the plan says prb checks its dz/dp every
    ``BIAS_EVERY`` iterations, and a run interrupted after some checks resumes to the same answer
    and standard errors (the checks' own checkpoint round trip: ``test_answer.py``). About 20
    s."""
    from services.solver.optimize.resolve import BIAS_EVERY
    from tests.support.jobs import SMALL_TRAINING
    from tests.support.jobs import run_job as _run

    # 32 iterations: a window of 18 whose halves can be tested for 6 scalars (2 (P + 2) = 16), so a
    # standard error (at 24 the longest window, 13, gives none)
    job = _job(method="ndrf-rhs", training=SMALL_TRAINING, iterations=32)
    reference = _run(job, tmp_path / "uninterrupted")
    plan = json.loads((tmp_path / "uninterrupted" / "plan.json").read_text())
    assert plan["recipe"]["optimizer"] == "levenberg-marquardt" and plan["recipe"]["bias_every"] == BIAS_EVERY
    assert any(d["what"] == "bias_every" for d in plan["recipe"]["decisions"])

    def stop_after_a_while():
        done = sorted((tmp_path / "interrupted" / "iterations").glob("*/record.json"))
        return "interrupted" if len(done) >= 15 else None

    out = tmp_path / "interrupted"
    assert _run(job, out, should_stop=stop_after_a_while)["status"] == "interrupted"
    resumed = _run(job, out, resume=True)
    events = [json.loads(line) for line in (out / "events.jsonl").read_text().splitlines()]
    assert [e["iteration"] for e in events if e["type"] == "resumed"][0] >= 12
    np.testing.assert_allclose(resumed["estimate"], reference["estimate"], rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(resumed["standard_error"], reference["standard_error"], rtol=1e-6, atol=1e-12)

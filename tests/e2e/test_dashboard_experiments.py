"""The Experiments pages in a real browser (Debian's Chromium, Playwright) against a real
``ndrf serve`` (embedded, 2 worker threads, API keys on): "sweep this job" from a job page, a
refused run shown next to its field, the experiment live to its end, the runs table sorted,
filtered and downloaded, the curves, the parallel coordinates, the accuracy-against-time plot of
a method sweep, two runs side by side; and the warm-up progress on a job page. Screenshots go to
the test's tmp_path."""

from __future__ import annotations

import csv
import io
import signal
import time

import pytest

from harness.cluster import small_job, start_api
from tests.support.browser import CHROMIUM, KEY, open_with_key

pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="needs Debian's Chromium at /usr/bin/chromium")


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dashboard-experiments")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), "NDRF_API_KEYS": KEY, "NDRF_EMBEDDED_WORKERS": "2"})
    yield api
    proc.kill(signal.SIGKILL)


def rows(page) -> list[dict]:
    return page.evaluate("""() => [...document.querySelectorAll('[data-testid=run-row]')].map((tr) => ({
        index: Number(tr.dataset.index), status: tr.dataset.status,
        error: tr.querySelector('[data-key=final_parameter_error]')?.textContent,
        method: tr.querySelector('[data-key="varied:method"]')?.textContent}))""")


def test_sweep_a_job_and_compare_its_runs(page, api, tmp_path):
    _, _, accepted = api.json("POST", "/v1/jobs", small_job("direct", iterations=3, name="red wall"))
    job_id = accepted["id"]
    api.wait_status(job_id, {"succeeded"}, 120)
    open_with_key(page, api, f"/#/jobs/{job_id}")
    page.get_by_test_id("sweep-link").click()
    method_row = page.locator("[data-testid=sweep-row][data-path=method]")
    method_row.wait_for()
    page.get_by_test_id("sweep-method-prb").check()                        # direct (the job's) and prb
    lr = page.locator("[data-testid=sweep-row][data-path=learning_rate]")
    lr.get_by_test_id("sweep-values").fill("0.05, -1")                     # one value no job accepts
    page.get_by_test_id("sweep-seeds").fill("1, 2")
    assert page.get_by_test_id("sweep-count").text_content() == "8 runs"
    page.get_by_test_id("sweep-submit").click()
    error = lr.locator(".field-error")
    error.wait_for(state="visible")
    assert "run 2" in error.text_content() and "greater than 0" in error.text_content()
    assert "runs[2].learning_rate" in page.get_by_test_id("sweep-banner").text_content()
    page.screenshot(path=tmp_path / "sweep-refused.png", full_page=True)
    assert api.json("GET", "/v1/experiments")[2]["items"] == []           # nothing was created or queued

    lr.get_by_test_id("sweep-enable").uncheck()
    assert page.get_by_test_id("sweep-count").text_content() == "4 runs"
    page.get_by_test_id("sweep-submit").click()
    page.wait_for_url("**/#/experiments/e*")
    exp_id = page.url.rsplit("/", 1)[1]

    # live: runs move through the table; at most 2 run at once; the page follows to the end
    seen_running, shot = 0, False
    deadline = time.monotonic() + 180
    while time.monotonic() < deadline:
        status = page.get_by_test_id("experiment-status").text_content()
        statuses = [r["status"] for r in rows(page)]
        seen_running = max(seen_running, statuses.count("running"))
        if not shot and "succeeded" in statuses:
            page.screenshot(path=tmp_path / "experiment-running.png", full_page=True)
            shot = True
        if status == "succeeded":
            break
        time.sleep(0.2)
    assert page.get_by_test_id("experiment-status").text_content() == "succeeded"
    page.wait_for_function("[...document.querySelectorAll('[data-testid=run-row]')]"
                           ".every(r => r.dataset.status === 'succeeded')")
    assert seen_running <= 2
    table = rows(page)
    assert sorted(r["index"] for r in table) == [0, 1, 2, 3] and {r["method"] for r in table} == {"direct", "prb"}

    # sort by final error, both ways; filter by method
    header = page.locator('[data-testid=sort-header][data-key=final_parameter_error]')
    header.click()
    errors = [float(r["error"]) for r in rows(page)]
    assert errors == sorted(errors)
    page.locator('[data-testid=sort-header][data-key=final_parameter_error]').click()
    assert [float(r["error"]) for r in rows(page)] == sorted(errors, reverse=True)
    page.get_by_test_id("runs-filter").fill("prb")
    assert {r["method"] for r in rows(page)} == {"prb"} and len(rows(page)) == 2
    assert page.get_by_test_id("runs-count").text_content() == "2 of 4 runs"
    page.get_by_test_id("runs-filter").fill("")

    # the CSV link downloads the runs as the API lists them
    response = page.request.get(page.get_by_test_id("csv-link").evaluate("a => a.href"))
    assert response.status == 200
    lines = list(csv.DictReader(io.StringIO(response.text())))
    assert len(lines) == 4 and {line["method"] for line in lines} == {"direct", "prb"}
    api_rows = api.json("GET", f"/v1/experiments/{exp_id}/runs")[2]
    assert [float(line["final_parameter_error"]) for line in lines] == [r["final_parameter_error"] for r in api_rows]

    # mean and spread per method; the curves coloured by a chosen field; parallel coordinates
    assert page.get_by_test_id("aggregate-row").count() == 2
    page.wait_for_function("document.querySelector('[data-testid=runs-loss-chart]')?.dataset.series === '4'")
    assert page.get_by_test_id("color-by").input_value() == "method"
    assert page.locator("[data-testid=curves-card] .legend-item").count() == 2
    page.get_by_test_id("color-by").select_option("seed")
    assert [t.strip() for t in page.locator("[data-testid=curves-card] .legend-item").all_text_contents()] == \
        ["seed = 1", "seed = 2"]
    page.get_by_test_id("x-axis").select_option("iteration")
    assert page.get_by_test_id("parallel-chart").get_attribute("data-lines") == "4"

    # a method sweep: accuracy against time, one mean curve per method
    accuracy = page.get_by_test_id("accuracy-chart")
    assert page.get_by_test_id("accuracy-card").is_visible() and accuracy.get_attribute("data-series") == "2"
    accuracy.scroll_into_view_if_needed()
    page.screenshot(path=tmp_path / "experiment-accuracy.png", full_page=True)

    # two runs side by side: renders and gradient images of each
    picks = page.locator("[data-testid=run-row] [data-testid=compare-pick]")
    picks.nth(0).check()
    page.locator("[data-testid=run-row] [data-testid=compare-pick]").nth(3).check()
    page.locator("[data-testid=compare-column]").nth(1).wait_for()
    assert page.locator("[data-testid=compare-column]").count() == 2
    page.wait_for_function("""[...document.querySelectorAll('[data-testid=compare-panel] img')]
        .every((img) => img.complete && img.naturalWidth === 16)""")
    assert page.locator("[data-testid=compare-gradient]").count() == 6          # 3 scalars x 2 runs
    page.get_by_test_id("compare-card").scroll_into_view_if_needed()
    page.screenshot(path=tmp_path / "experiment-compare.png", full_page=True)

    # every run links to its job page, which links back
    page.locator("[data-testid=run-link]").first.click()
    page.wait_for_url("**/#/jobs/*")
    page.get_by_test_id("experiment-link").wait_for()
    assert exp_id in page.get_by_test_id("experiment-link").get_attribute("href")

    # the experiments list shows it finished, with its progress over runs
    page.get_by_test_id("nav-experiments").click()
    row = page.locator(f'[data-testid=experiment-row][data-experiment-id="{exp_id}"]')
    row.wait_for()
    assert row.get_attribute("data-status") == "succeeded"
    assert row.get_by_test_id("experiment-progress").text_content() == "4 / 4"
    page.screenshot(path=tmp_path / "experiments.png", full_page=True)


def test_the_job_page_shows_warmup_progress(page, api, tmp_path):
    job = small_job("ndrf-lhs", iterations=2, name="long warm-up")
    job["training"] = dict(job["training"], warmup_steps=3000)
    _, _, accepted = api.json("POST", "/v1/jobs", job)
    job_id = accepted["id"]
    try:
        open_with_key(page, api, f"/#/jobs/{job_id}")
        warmup = page.get_by_test_id("warmup")
        warmup.wait_for(state="visible", timeout=120_000)
        first = int(page.get_by_test_id("warmup-text").get_attribute("data-steps"))
        page.wait_for_function(f"Number(document.querySelector('[data-testid=warmup-text]').dataset.steps) > {first}",
                               timeout=60_000)
        text = page.get_by_test_id("warmup-text").text_content()
        assert "/ 3000 training steps" in text and "residual" in text
        page.screenshot(path=tmp_path / "warmup.png", full_page=True)
    finally:
        api.json("POST", f"/v1/jobs/{job_id}/cancel")
    page.wait_for_function("document.querySelector('[data-testid=status-badge]')?.textContent === 'canceled'",
                           timeout=60_000)
    assert page.get_by_test_id("warmup").is_hidden()

"""The web dashboard in a real browser: Debian's Chromium driven by Playwright against a real
``ndrf serve`` (embedded mode, API keys on). The key prompt, the submit form and its field errors,
the job page following the SSE stream, the gradient slider, cancel, the live jobs list, and a
texture job's texture charts.

Screenshots go to the test's tmp_path; with NDRF_UPDATE_SCREENSHOTS=1 the job page is also
written to docs/assets/dashboard.png for the docs."""

from __future__ import annotations

import os
import re
import shutil
import signal
import time

import pytest

from harness.cluster import ROOT, small_job, start_api
from tests.support.browser import CHROMIUM, KEY, open_with_key
from tests.support.scenes import QUAD_OBJ, UPLOAD_MATERIALS, UPLOAD_XML

FINISHED = ("succeeded", "failed", "canceled")


pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="needs Debian's Chromium at /usr/bin/chromium "
                                                              "(apt-get install chromium)")


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dashboard")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), "NDRF_API_KEYS": KEY})
    yield api
    proc.kill(signal.SIGKILL)


def fill_small_job(page, *, name: str, spp: str = "4", init: str = "0.3", iterations: str = "20"):
    """The submit form, filled for a job that runs in seconds on 2 cores (cornell-box, 16x16)."""
    page.get_by_test_id("field-scene.builtin").select_option("cornell-box")
    row = page.locator('[data-testid=param-row][data-key="red.reflectance.value"]')
    row.get_by_test_id("param-enable").check()
    row.get_by_test_id("param-init").fill(init)
    row.get_by_test_id("param-target").fill("0.57, 0.04, 0.04")
    page.get_by_test_id("field-name").fill(name)
    page.get_by_test_id("field-method").select_option("ndrf-lhs")
    page.locator("details.advanced > summary").click()        # images_every lives under Advanced
    for path, value in {"iterations": iterations, "learning_rate": "0.05", "render.spp": spp,
                        "render.gradient_spp": "4", "render.resolution.width": "16", "render.resolution.height": "16",
                        "targets.synthetic.spp": "16", "training.warmup_steps": "10",
                        "training.steps_per_iteration": "2", "training.residual_points": "256",
                        "training.incident_samples": "4", "images_every": "1", "seed": "1"}.items():
        page.get_by_test_id(f"field-{path}").fill(value)


def job_page_state(page) -> dict:
    return page.evaluate("""() => {
        const q = (id) => document.querySelector(`[data-testid="${id}"]`);
        return {count: Number(q('iteration-counter')?.dataset.value ?? -1),
                points: Number(q('loss-chart')?.dataset.points ?? 0),
                status: q('status-badge')?.textContent ?? '',
                connection: q('connection')?.textContent ?? ''};
    }""")


def image_loaded(page, selector: str) -> bool:
    return page.eval_on_selector(selector, "img => img.complete && img.naturalWidth > 0")


def test_the_dashboard_runs_under_its_content_security_policy(browser, api):
    """The CSP kept (no bypass): the key dialog, the job list and the submit form with its scene
    parameters work, and the page reports no violation."""
    context = browser.new_context(viewport={"width": 1360, "height": 900})
    page = context.new_page()
    page.set_default_timeout(30_000)
    problems: list[str] = []
    page.on("pageerror", lambda exc: problems.append(str(exc)))
    page.on("console", lambda msg: problems.append(msg.text) if "Content Security Policy" in msg.text else None)
    open_with_key(page, api)
    page.get_by_test_id("new-job").click()
    page.locator('[data-testid=param-row][data-key="red.reflectance.value"]').wait_for()
    page.goto(api.base + "/#/experiments")
    page.wait_for_load_state("networkidle")
    context.close()
    assert not problems, problems


def test_submit_a_job_and_watch_it_live(page, api, tmp_path):
    open_with_key(page, api)
    page.get_by_test_id("new-job").click()
    page.locator('[data-testid=param-row][data-key="red.reflectance.value"]').wait_for()
    fill_small_job(page, name="red wall")
    page.screenshot(path=tmp_path / "submit.png", full_page=True)
    page.get_by_test_id("submit-button").click()
    page.wait_for_url(re.compile(r".*#/jobs/[0-9a-f]{20}$"))
    job_id = page.url.rsplit("/", 1)[1]

    # the counter and the loss curve advance as the SSE stream delivers iterations
    seen, deadline, shot = [], time.monotonic() + 120, False
    while time.monotonic() < deadline:
        state = job_page_state(page)
        seen.append(state)
        if state["status"] in FINISHED:
            break
        if not shot and state["count"] >= 8:
            page.screenshot(path=tmp_path / "job-running.png", full_page=True)
            shot = True
        time.sleep(0.1)
    final = seen[-1]
    assert final["status"] == "succeeded", final
    live = [s for s in seen if s["status"] == "running" and s["count"] > 0]
    counts = sorted({s["count"] for s in live})
    assert len(counts) >= 3, f"the iteration counter did not advance while running: {counts}"
    assert [s["count"] for s in live] == sorted(s["count"] for s in live)         # never backwards
    assert live[-1]["points"] > live[0]["points"] >= 1                              # the loss curve grew
    assert any(s["connection"] == "live" for s in live), "the SSE stream was never open"
    assert final["count"] == 20 and final["points"] == 20
    assert page.get_by_test_id("iteration-counter").text_content() == "20 / 20"
    assert page.get_by_test_id("cancel-button").is_hidden()
    # the answer: why the run stopped, the estimate and its standard error beside the last iterate,
    # each parameter's estimate with its band of ± 2 standard errors
    page.wait_for_function("document.querySelector('[data-testid=stop-reason]')?.textContent.includes('cap of 20')")
    header = page.locator("[data-testid=parameter-table] thead").text_content()
    assert "estimate" in header and "± SE" in header and "last iterate" in header
    assert page.locator("[data-testid=parameter-charts] path.chart-band").count() >= 3

    # history and images: the render beside the target, the gradient of a chosen iteration
    page.wait_for_function("document.querySelector('[data-testid=render-image]').naturalWidth > 0")
    page.wait_for_function("document.querySelector('[data-testid=target-image]').naturalWidth > 0")
    slider = page.get_by_test_id("iteration-slider")
    assert slider.get_attribute("max") == "19"
    slider.focus()
    page.keyboard.press("Home")
    for _ in range(3):
        page.keyboard.press("ArrowRight")
    assert page.get_by_test_id("slider-iteration").text_content() == "#3"
    gradient = '[data-testid=gradient-image][data-scalar="0"]'
    assert "/iterations/3/gradients/0.png" in page.get_attribute(gradient, "src")
    page.wait_for_function(f"document.querySelector('{gradient}').naturalWidth > 0")
    assert image_loaded(page, gradient) and page.locator("[data-testid=gradient-image]").count() == 3
    assert page.locator(".colorbar-labels").first.text_content().startswith("−")
    page.screenshot(path=tmp_path / "job-gradient-3.png", full_page=True)

    # downloads authenticate by URL with the job's read token (?token=), like the images and the events
    link = page.locator("[data-testid=downloads] a", has_text="Latest checkpoint")
    response = page.request.get(link.evaluate("a => a.href"))
    assert response.status == 200 and len(response.body()) > 1000
    npy = page.locator('[data-testid=gradient-image][data-scalar="1"] ~ a[data-role=npy]')
    response = page.request.get(npy.evaluate("a => a.href"))
    assert response.status == 200 and response.body()[:6] == b"\x93NUMPY"
    assert job_id in page.get_by_test_id("downloads").inner_html()

    # reload: history comes from GET /iterations, the same state
    page.reload()
    page.wait_for_function("document.querySelector('[data-testid=loss-chart]')?.dataset.points === '20'")
    assert job_page_state(page)["count"] == 20

    assert page.get_by_test_id("slider-iteration").text_content() == "#19 (latest)"
    page.evaluate("window.scrollTo(0, 0)")
    page.mouse.move(0, 0)
    page.wait_for_function("[...document.querySelectorAll('[data-testid=gradient-image]')].every(i => i.naturalWidth > 0)")
    page.screenshot(path=tmp_path / "job.png", full_page=True)
    docs = ROOT / "docs" / "assets" if os.environ.get("NDRF_UPDATE_SCREENSHOTS") else tmp_path / "docs"
    docs.mkdir(exist_ok=True)
    page.set_viewport_size({"width": 1360, "height": 1330})
    page.screenshot(path=docs / "dashboard.png")
    if docs != tmp_path / "docs":
        shutil.copy(docs / "dashboard.png", tmp_path / "dashboard.png")

    # the jobs list shows the job, finished, with its final error against the synthetic target
    page.get_by_test_id("nav-jobs").click()
    row = page.locator(f'[data-testid=job-row][data-job-id="{job_id}"]')
    row.wait_for()
    assert row.get_attribute("data-status") == "succeeded"
    assert row.get_by_test_id("job-progress").text_content() == "20 / 20"
    assert re.search(r"\d", row.locator("td").nth(8).text_content())
    page.screenshot(path=tmp_path / "jobs.png", full_page=True)


def test_a_refused_job_shows_each_error_next_to_its_field(page, api, tmp_path):
    jobs_before = len(api.json("GET", "/v1/jobs")[2]["items"])
    open_with_key(page, api, "/#/submit", wrong_first=True)
    page.locator('[data-testid=param-row][data-key="red.reflectance.value"]').wait_for()

    fill_small_job(page, name="bad spp", spp="0")                     # schema: render.spp >= 1
    page.get_by_test_id("submit-button").click()
    error = page.locator('[data-testid=field-error][data-for="render.spp"]')
    error.wait_for(state="visible")
    assert "greater than or equal to 1" in error.text_content()
    assert "has-error" in page.locator('.field[data-field="render.spp"]').get_attribute("class")
    wrapper = page.locator('.field[data-field="render.spp"]')                     # next to its input
    assert wrapper.get_by_test_id("field-render.spp").count() == 1 and wrapper.get_by_test_id("field-error").is_visible()
    assert page.get_by_test_id("form-banner").is_visible()
    page.screenshot(path=tmp_path / "error-spp.png", full_page=True)

    page.get_by_test_id("field-render.spp").fill("4")                 # preflight: 2 values for an RGB
    row = page.locator('[data-testid=param-row][data-key="red.reflectance.value"]')
    row.get_by_test_id("param-init").fill("0.1, 0.2")
    page.get_by_test_id("submit-button").click()
    error = row.locator('[data-testid=field-error][data-for="parameters[0].init"]')
    error.wait_for(state="visible")
    assert "has 2 values" in error.text_content()
    assert page.locator('[data-testid=field-error][data-for="render.spp"]').is_hidden()
    page.screenshot(path=tmp_path / "error-init.png", full_page=True)

    assert "#/submit" in page.url
    assert len(api.json("GET", "/v1/jobs")[2]["items"]) == jobs_before           # nothing was queued


def test_cancel_a_long_job_from_its_page(page, api, tmp_path):
    _, _, accepted = api.json("POST", "/v1/jobs", small_job(iterations=2000, name="long run"))
    job_id = accepted["id"]
    open_with_key(page, api)

    # the jobs list updates without a reload
    progress = page.locator(f'[data-testid=job-row][data-job-id="{job_id}"] [data-testid=job-progress]')
    progress.wait_for()
    first = int(progress.text_content().split("/")[0])
    page.wait_for_function(f"""() => {{
        const el = document.querySelector('[data-job-id="{job_id}"] [data-testid=job-progress]');
        return el && parseInt(el.textContent) >= {first} + 2;
    }}""", timeout=90_000)

    page.locator(f'[data-testid=job-row][data-job-id="{job_id}"] a.job-name').click()
    page.wait_for_url(f"**/#/jobs/{job_id}")
    page.wait_for_function("Number(document.querySelector('[data-testid=iteration-counter]')?.dataset.value) >= 2")
    assert page.get_by_test_id("status-badge").text_content() == "running"
    page.get_by_test_id("cancel-button").click()
    page.wait_for_function("document.querySelector('[data-testid=status-badge]')?.textContent === 'canceled'",
                           timeout=60_000)
    assert page.get_by_test_id("cancel-button").is_hidden()
    page.screenshot(path=tmp_path / "canceled.png", full_page=True)
    job = api.json("GET", f"/v1/jobs/{job_id}")[2]
    assert job["status"] == "canceled" and 2 <= job["iteration"] + 1 < 2000
    assert page.get_by_test_id("iteration-counter").get_attribute("data-value") == str(job["iteration"] + 1)


def test_upload_a_scene_folder_and_a_target_photograph(page, api, tmp_path):
    import numpy as np
    from PIL import Image

    folder = tmp_path / "my-scene"
    (folder / "meshes").mkdir(parents=True)
    (folder / "scene.xml").write_text(UPLOAD_XML)
    (folder / "materials.xml").write_text(UPLOAD_MATERIALS)
    (folder / "meshes" / "quad.obj").write_text(QUAD_OBJ)
    photo = tmp_path / "photo.png"
    Image.fromarray(np.full((12, 16, 3), 120, np.uint8)).save(photo)          # the film is 16x12

    open_with_key(page, api, "/#/submit")
    page.get_by_test_id("scene-mode-upload").check()
    page.get_by_test_id("field-scene.folder").set_input_files(folder)      # webkitRelativePath: my-scene/...
    row = page.locator('[data-testid=param-row][data-key="paint.reflectance.value"]')
    row.wait_for()
    assert page.get_by_test_id("field-scene.xml").input_value() == "my-scene/scene.xml"
    assert "meshes/quad.obj" in page.locator('[data-field="scene.files"]').text_content()
    row.get_by_test_id("param-enable").check()
    row.get_by_test_id("param-init").fill("0.5")
    page.get_by_test_id("target-mode-images").check()
    page.get_by_test_id("target-image-0").set_input_files(photo)
    page.get_by_test_id("field-method").select_option("direct")
    for path, value in {"iterations": "3", "render.spp": "4", "render.gradient_spp": "4"}.items():
        page.get_by_test_id(f"field-{path}").fill(value)
    page.screenshot(path=tmp_path / "upload.png", full_page=True)
    page.get_by_test_id("submit-button").click()
    page.wait_for_url(re.compile(r".*#/jobs/[0-9a-f]{20}$"))
    page.wait_for_function("document.querySelector('[data-testid=status-badge]')?.textContent === 'succeeded'",
                           timeout=60_000)
    page.wait_for_function("document.querySelector('[data-testid=target-image]').naturalWidth === 16")
    job = api.json("GET", f"/v1/jobs/{page.url.rsplit('/', 1)[1]}")[2]
    assert job["scene"] == "xml" and job["method"] == "direct" and job["target_values"] is None
    assert page.get_by_test_id("parameter-error").text_content() == "—"               # no known target
    page.screenshot(path=tmp_path / "upload-job.png", full_page=True)


def test_a_texture_job_charts_its_texture_summaries(page, api, tmp_path):
    """A pure texture job (an uploaded 8 x 8 textured box, no listed scalar): the parameters card
    charts the texture's mean per channel with min, max and the target's mean, its PSNR and the
    RMS of dz/dp over the iterations, with a table row, instead of waiting for scalars."""
    from services.solver.scene.textured import KEY, write_textured_box
    from services.uploads.pack import pack_scene

    xml, files = pack_scene(write_textured_box(tmp_path / "scene", size=8, views=1, film=16))
    job = {"name": "texture", "scene": {"xml": xml, "files": files}, "parameters": [{"key": KEY, "init": 0.5}],
           "targets": {"synthetic": {"values": {KEY: None}, "spp": 8}}, "iterations": 4,
           "render": {"spp": 4, "gradient_spp": 4}, "seed": 1}
    status, _, accepted = api.json("POST", "/v1/jobs", job)
    assert status == 202, accepted
    api.wait_status(accepted["id"], {"succeeded"}, 120)
    records = api.json("GET", f"/v1/jobs/{accepted['id']}/iterations")[2]
    assert len(records) == 4 and all(r["parameters"] == [] for r in records)

    open_with_key(page, api, f"/#/jobs/{accepted['id']}")
    charts = page.locator(f'[data-testid=texture-chart][data-key="{KEY}"]')
    charts.wait_for()
    psnr = charts.locator(f'[data-testid=texture-psnr-chart][data-key="{KEY}"]')
    page.wait_for_function("() => document.querySelector('[data-testid=texture-psnr-chart]')?.dataset.points === '4'")
    assert psnr.locator("path.chart-line").count() == 1                         # one PSNR series
    mean = charts.locator(f'[data-testid=texture-mean-chart][data-key="{KEY}"]')
    assert mean.get_attribute("data-points") == "4"
    assert mean.locator("path.chart-line").count() == 5                         # R, G, B, min, max
    assert mean.locator("line.chart-guide").count() == 3                        # the target's mean per channel
    assert charts.locator("[data-testid=texture-gradient-chart]").get_attribute("data-points") == "4"
    row = page.locator(f'[data-testid=texture-row][data-key="{KEY}"]')
    cells = row.locator("td").all_text_contents()
    assert cells[:2] == [KEY, "8×8×3"] and len(cells[2].split(", ")) == 3
    assert float(cells[3]) == pytest.approx(records[-1]["textures"][KEY]["psnr"], rel=1e-2)
    assert "appear when the job starts" not in page.get_by_test_id("parameters-card").text_content()
    assert page.get_by_test_id("parameter-error").text_content() == "—"         # no listed scalar to compare
    # no per-scalar dI/dp block nor P x H x W x 3 download: the job lists no scalar (its gradient is a texture)
    assert page.get_by_text("Gradient images dI/dp").is_hidden()
    assert page.locator('a[href*="gradients.npy"]:visible').count() == 0
    assert page.locator('[data-testid=texture-grid] figure[data-texture]').count() == 2   # the texture and its dz/dp
    page.screenshot(path=tmp_path / "texture-job.png", full_page=True)

"""The job page's orbit viewer in Chromium against a real ``ndrf serve`` (embedded, API keys on):
it asks the views API for the fields from sensor 0, shows the radiance and the picked scalar's
gradient image, and a drag moves the camera about the target and renders the view again (from
the warm view child)."""

from __future__ import annotations

import json
import signal

import pytest

from tests.support.browser import CHROMIUM, KEY, open_with_key
from tests.support.service import small_job, start_api

pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="needs Debian's Chromium at /usr/bin/chromium")


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dashboard-orbit")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), "NDRF_API_KEYS": KEY})
    yield api
    proc.kill(signal.SIGKILL)


def shown(page, testid: str) -> str:
    """The data URL an image shows once it has decoded ('' before)."""
    return page.eval_on_selector(f"[data-testid={testid}]",
                                 "img => img.complete && img.naturalWidth > 0 ? img.src : ''")


@pytest.mark.slow  # a job, then views in a sandboxed child
def test_the_orbit_viewer_renders_the_fields_and_a_drag_renders_them_again(page, api, tmp_path):
    _, _, accepted = api.json("POST", "/v1/jobs", small_job("ndrf-lhs", iterations=2, name="orbit"))
    job_id = accepted["id"]
    api.wait_status(job_id, {"succeeded"}, 600)
    views: list[dict] = []
    page.on("request", lambda r: views.append(json.loads(r.post_data)) if r.url.endswith("/views")
            and r.method == "POST" else None)
    open_with_key(page, api, f"/#/jobs/{job_id}")
    page.get_by_test_id("orbit-open").click()
    page.get_by_test_id("orbit-stage").wait_for(state="visible", timeout=300_000)
    page.wait_for_function("() => document.querySelector('[data-testid=orbit-image]').naturalWidth > 0")
    first, radiance = shown(page, "orbit-image"), shown(page, "orbit-radiance")
    assert first.startswith("data:image/png;base64,") and radiance.startswith("data:image/png;base64,")
    assert views[0] == {"sensor": 0, "resolution": [128, 128], "spp": 4, "inline": True}
    options = page.get_by_test_id("orbit-scalar").locator("option").all_text_contents()
    assert len(options) == 3 and all("red.reflectance.value" in o for o in options)
    page.get_by_test_id("orbit-scalar").select_option("2")          # another scalar: its own image
    assert shown(page, "orbit-image") not in ("", first)
    before = page.get_by_test_id("orbit-card").get_attribute("data-camera")
    start = json.loads(before)

    box = page.get_by_test_id("orbit-image").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 40, y + 10, steps=4)
    page.mouse.up()
    page.wait_for_function("before => document.querySelector('[data-testid=orbit-card]').dataset.camera !== before",
                           arg=before, timeout=300_000)
    page.wait_for_function("() => /^128×128 in \\d+ ms \\(warm\\)$/.test("
                           "document.querySelector('[data-testid=orbit-ms]').textContent)", timeout=300_000)
    moved = [v for v in views[1:] if "origin" in v]
    assert moved and moved[0]["resolution"] == [64, 64] and moved[0]["spp"] == 1      # previews while dragging
    assert moved[-1]["resolution"] == [128, 128] and moved[-1]["origin"] != start     # the full view on release
    assert shown(page, "orbit-image") not in ("", first)
    page.screenshot(path=tmp_path / "orbit.png", full_page=True)

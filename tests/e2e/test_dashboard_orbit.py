"""The job page's orbit viewer in Chromium against a real ``ndrf serve`` (embedded, API keys on):
it asks the views API for the fields from sensor 0, shows the radiance and the picked scalar's
gradient image, and a drag moves the camera about the target and renders the view again (from
the warm view child)."""

from __future__ import annotations

import base64
import json
import signal
import struct
import zlib

import pytest

from harness.cluster import small_job, start_api
from tests.support.browser import CHROMIUM, KEY, open_with_key

pytestmark = pytest.mark.skipif(not CHROMIUM.exists(), reason="needs Debian's Chromium at /usr/bin/chromium")


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dashboard-orbit")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), "NDRF_API_KEYS": KEY})
    yield api
    proc.kill(signal.SIGKILL)


def png_bytes(color: tuple[int, int, int]) -> bytes:
    """A 2x2 RGB PNG of one colour."""
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    rows = b"".join(b"\x00" + bytes(color) * 2 for _ in range(2))
    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", 2, 2, 8, 2, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b""))


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
    page.wait_for_function("first => { const img = document.querySelector('[data-testid=orbit-image]');"
                           " return img.complete && img.naturalWidth > 0 && img.src !== first; }", arg=first)
    before = page.get_by_test_id("orbit-card").get_attribute("data-camera")
    start = json.loads(before)

    # the card sits below the fold of the 1280x720 viewport: a press outside it is not always
    # delivered to the image, so bring it into view first
    page.get_by_test_id("orbit-image").scroll_into_view_if_needed()
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
    after = page.get_by_test_id("orbit-image").get_attribute("src")
    assert after.startswith("data:image/png;base64,") and after != first
    page.screenshot(path=tmp_path / "orbit.png", full_page=True)


@pytest.fixture(scope="module")
def open_api(tmp_path_factory):
    """``ndrf serve`` without API keys (loopback), over a store the test writes a job record into."""
    tmp = tmp_path_factory.mktemp("dashboard-orbit-open")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store")})
    yield api, tmp / "store"
    proc.kill(signal.SIGKILL)


# a 2x2 PNG per image: red, green, blue
PNGS = {name: "data:image/png;base64," + base64.b64encode(png_bytes(color)).decode()
        for name, color in (("radiance.png", (200, 0, 0)), ("gradient-0.png", (0, 200, 0)),
                            ("gradient-1.png", (0, 0, 200)))}


def test_the_orbit_viewer_drives_the_views_api(page, open_api):
    """The viewer's side alone (the views API answered by the test): the sensor view first, the
    scalar picker, previews while dragging about the target, the full view on release."""
    from schemas.job import JobSpec
    from services.jobs.service import JobService
    from services.queue.local import LocalEventBus, LocalJobQueue
    from services.store.local import FolderStore

    api, store = open_api
    record, _ = JobService(FolderStore(store), LocalJobQueue(), LocalEventBus()).submit(
        JobSpec.model_validate(small_job("ndrf-lhs", iterations=2, name="orbit, answered by the test")))
    asked: list[dict] = []

    def answer(route):
        body = json.loads(route.request.post_data)
        asked.append(body)
        camera = {"origin": [0.0, 0.0, 4.0], "target": [0.0, 0.0, 0.0], "up": [0.0, 1.0, 0.0], "fov": 40.0}
        camera = {**camera, **{k: body[k] for k in ("origin", "target", "up", "fov") if k in body},
                  "resolution": body["resolution"]}
        route.fulfill(status=201, content_type="application/json", body=json.dumps({
            "id": f"{len(asked):012x}", "files": {}, "images": PNGS, "scalars": ["a[0]", "a[1]"],
            "seconds": {"scene": 0.1, "fields": 0.1}, "iteration": 2, "camera": camera, "warm": len(asked) > 1}))

    page.route(f"**/v1/jobs/{record.id}/views", answer)
    page.goto(f"{api.base}/#/jobs/{record.id}")
    page.get_by_test_id("orbit-open").click()
    page.wait_for_function("() => document.querySelector('[data-testid=orbit-image]').naturalWidth > 0")
    assert asked == [{"sensor": 0, "resolution": [128, 128], "spp": 4, "inline": True}]
    assert page.get_by_test_id("orbit-image").get_attribute("src") == PNGS["gradient-0.png"]
    assert page.get_by_test_id("orbit-radiance").get_attribute("src") == PNGS["radiance.png"]
    assert page.get_by_test_id("orbit-scalar").locator("option").all_text_contents() == ["a[0]", "a[1]"]
    page.get_by_test_id("orbit-scalar").select_option("1")
    assert page.get_by_test_id("orbit-image").get_attribute("src") == PNGS["gradient-1.png"]
    assert "(child started)" in page.get_by_test_id("orbit-ms").text_content()

    # the card sits below the fold of the 1280x720 viewport: a press outside it is not always
    # delivered to the image, so bring it into view first
    page.get_by_test_id("orbit-image").scroll_into_view_if_needed()
    box = page.get_by_test_id("orbit-image").bounding_box()
    x, y = box["x"] + box["width"] / 2, box["y"] + box["height"] / 2
    page.mouse.move(x, y)
    page.mouse.down()
    page.mouse.move(x + 60, y + 20, steps=6)
    page.mouse.up()
    page.wait_for_function("() => /^128×128 in \\d+ ms \\(warm\\)$/.test("
                           "document.querySelector('[data-testid=orbit-ms]').textContent)")
    previews, final = asked[1:-1], asked[-1]
    assert previews and all(v["resolution"] == [64, 64] and v["spp"] == 1 for v in previews)
    assert final["resolution"] == [128, 128] and final["spp"] == 4 and final["target"] == [0.0, 0.0, 0.0]
    origin = final["origin"]
    assert abs(sum(c * c for c in origin) ** 0.5 - 4.0) < 1e-9          # the same distance from the target
    assert origin[0] < -0.5 and origin[1] > 0.1                         # turned (yaw) and raised (pitch)

"""Debian's Chromium for the dashboard tests (Playwright drives it; no browser download), and the
API key those tests serve the dashboard with."""

from __future__ import annotations

from pathlib import Path

CHROMIUM = Path("/usr/bin/chromium")
ARGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
        "--disable-background-networking", "--disable-component-update", "--disable-sync"]

#: The API key of the dashboard tests' server.
KEY = "dash-key"


def open_with_key(page, api, route: str = "/", wrong_first: bool = False):
    """Open the dashboard; the first API call gets a 401 and the page asks for the key once."""
    page.goto(api.base + route)
    dialog = page.get_by_test_id("api-key-dialog")
    dialog.wait_for(state="visible")
    if wrong_first:                                   # refused: asked again, saying so
        page.get_by_test_id("api-key-input").fill("not-the-key")
        page.get_by_test_id("api-key-submit").click()
        page.locator("#key-error").wait_for(state="visible")
    page.get_by_test_id("api-key-input").fill(KEY)
    page.get_by_test_id("api-key-submit").click()
    dialog.wait_for(state="hidden")
    assert page.evaluate("sessionStorage.getItem('ndrf.apiKey')") == KEY

"""Fixtures of the end-to-end tier shared by its dashboard tests."""

from __future__ import annotations

import pytest


@pytest.fixture()
def page(browser):
    """A fresh browser context (empty sessionStorage, so the page asks for the key again); fails
    the test on any uncaught error in the page."""
    # bypass_csp: Playwright's wait_for_function evaluates strings in the page, which the dashboard's
    # CSP forbids (test_the_dashboard_runs_under_its_content_security_policy keeps it)
    context = browser.new_context(viewport={"width": 1360, "height": 900}, bypass_csp=True)
    page = context.new_page()
    page.set_default_timeout(30_000)
    errors: list[str] = []
    page.on("pageerror", lambda exc: errors.append(str(exc)))
    yield page
    context.close()
    assert not errors, f"uncaught errors in the page: {errors}"

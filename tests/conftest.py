"""Shared fixtures. Mitsuba's variant is selected once per session, lazily."""

from __future__ import annotations

import pytest


@pytest.fixture(scope="session")
def mi():
    from services.backend import use_mitsuba, use_torch

    use_torch()
    return use_mitsuba()

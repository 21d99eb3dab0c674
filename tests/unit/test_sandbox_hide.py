"""The sandbox never hides the code its child runs (services/jobs/sandbox.py): a hidden folder that
holds the interpreter or the product is refused with its reason, not left to fail later with a
ModuleNotFoundError; and scene checks work in a folder of their own, never directly in /tmp."""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import pytest

from services.jobs.preflight import checks_folder
from services.jobs.sandbox import SandboxUnavailable, _refuse_to_hide_the_code


def test_a_folder_holding_the_interpreter_or_the_product_is_not_hidden():
    with pytest.raises(SandboxUnavailable, match="holds"):
        _refuse_to_hide_the_code([Path(sys.prefix).resolve().parent])
    with pytest.raises(SandboxUnavailable, match="outside the installation"):
        _refuse_to_hide_the_code([Path(__file__).resolve().parents[2]])
    _refuse_to_hide_the_code([Path(tempfile.gettempdir()).resolve() / "ndrf-checks", Path("/run")])


def test_scene_checks_have_a_parent_folder_of_their_own():
    folder = checks_folder()
    assert folder.parent == Path(tempfile.gettempdir()) and folder.is_dir()

"""The dashboard's ``FINISHED`` is the service's: ``static/js/statuses.js`` is written from
``schemas.records.FINISHED`` (issue 45: it was written out twice in the scripts)."""

from __future__ import annotations

import json
import re

from fastapi import FastAPI
from fastapi.testclient import TestClient

from api.dashboard import STATIC, mount
from schemas.experiments import ExperimentStatus
from schemas.records import FINISHED


def test_the_dashboard_reads_finished_from_the_schema():
    app = FastAPI()
    mount(app)
    response = TestClient(app).get("/static/js/statuses.js")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/javascript")
    served = re.search(r"export const FINISHED = new Set\((\[.*?\])\);", response.text)
    assert served and set(json.loads(served.group(1))) == {str(s) for s in FINISHED}
    # the experiment page tests an experiment's status against the same set
    assert {str(s) for s in ExperimentStatus if s.finished} == {str(s) for s in FINISHED}


def test_no_script_writes_the_finished_statuses_out_again():
    scripts = {path.name: path.read_text() for path in (STATIC / "js").rglob("*.js")}
    assert "statuses.js" not in scripts          # served, not a file that could drift
    listed = [name for name, text in scripts.items() if re.search(r'\[\s*"succeeded",\s*"failed",\s*"canceled"\s*\]', text)]
    assert listed == []

"""The web dashboard, served by the API itself at ``/`` (static files, no build step).

One script is written here rather than kept in ``static/js``: ``statuses.js``, the job statuses
that end a job (``schemas.records.FINISHED``), so the dashboard and the service share one
definition."""

from __future__ import annotations

import json
from pathlib import Path

from fastapi import FastAPI
from fastapi.responses import FileResponse, Response
from fastapi.staticfiles import StaticFiles

from schemas.records import FINISHED

STATIC = Path(__file__).parent / "static"


def statuses_module() -> str:
    """``static/js/statuses.js``: ``FINISHED``, the statuses after which a job (or an experiment,
    whose statuses end the same way) changes no more."""
    finished = json.dumps(sorted(str(status) for status in FINISHED))
    return ("// Written by api/dashboard/__init__.py from schemas.records.FINISHED.\n"
            f"export const FINISHED = new Set({finished});\n")


def mount(app: FastAPI) -> None:
    if not (STATIC / "index.html").is_file():
        return

    @app.get("/", include_in_schema=False)
    def index():
        return FileResponse(STATIC / "index.html")

    @app.get("/static/js/statuses.js", include_in_schema=False)
    def statuses():            # before the mount: it would answer 404 for a file it does not hold
        return Response(statuses_module(), media_type="text/javascript")

    app.mount("/static", StaticFiles(directory=STATIC), name="static")

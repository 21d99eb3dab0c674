"""Errors shared by the solver, the service and the CLI (no heavy imports)."""

from __future__ import annotations


class JobError(ValueError):
    """A job that cannot run; ``field`` is the JSON path of the offending field."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message

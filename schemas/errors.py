"""The one error for input that cannot run, shared by the solver, the service and the CLI."""

from __future__ import annotations


class InvalidJob(ValueError):
    """A job (or an uploaded scene) that cannot run; ``field`` is the JSON path of the offending
    part of the job file (``parameters[0].key``, ``scene.files[m.ply]``), ``message`` says what is
    wrong and what is allowed. The API answers it with a 422 naming the field."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message

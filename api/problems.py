"""Errors as RFC 9457 problem details (``application/problem+json``).

Every error response of the API has this shape; validation errors list each offending field::

    {"type": "/problems/invalid-job", "title": "Invalid job", "status": 422,
     "detail": "render.spp: Input should be greater than or equal to 1",
     "errors": [{"field": "render.spp", "message": "..."}]}
"""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from schemas.validation import field_path
from services.experiments.state import ExperimentConflict, UnknownExperiment
from services.jobs.state import Conflict, UnknownJob

log = logging.getLogger(__name__)

PROBLEM_JSON = "application/problem+json"


class FieldError(BaseModel):
    field: str = Field(description="JSON path of the offending field, e.g. 'parameters[0].init'.")
    message: str = Field(description="What is wrong and what is allowed.")


class ProblemDetails(BaseModel):
    """RFC 9457 problem details."""

    type: str = Field("about:blank", description="URI reference identifying the problem type.")
    title: str = Field(description="Short summary of the problem type.")
    status: int = Field(description="HTTP status code.")
    detail: str | None = Field(None, description="Explanation specific to this occurrence.")
    instance: str | None = Field(None, description="The request path.")
    errors: list[FieldError] | None = Field(None, description="Offending fields (validation problems): at most "
                                                                "NDRF_MAX_VALIDATION_ERRORS of them.")
    more_errors: int | None = Field(None, description="Validation errors found but not listed in `errors` "
                                                      "(the list is capped).")


class ProblemError(Exception):
    """Raise from a route to answer with a problem document."""

    def __init__(self, status: int, title: str, detail: str | None = None, *, slug: str | None = None,
                 errors: list[tuple[str, str]] | None = None, headers: dict[str, str] | None = None):
        super().__init__(detail or title)
        self.status, self.title, self.detail, self.slug = status, title, detail, slug
        self.errors, self.headers = errors, headers


def conflict(slug: str) -> dict:
    """A route's ``409`` (``responses={409: conflict("job-finished")}``): the conflict a service
    raises in that route (:class:`~services.jobs.state.Conflict`,
    :class:`~services.experiments.state.ExperimentConflict`) is answered with the problem type
    ``/problems/{slug}``, which OpenAPI lists as the response's ``x-problem-type``."""
    return {"model": ProblemDetails, "x-problem-type": f"/problems/{slug}"}


def _conflict_slug(request: Request) -> str | None:
    """The slug the matched route declares for its ``409`` (:func:`conflict`), if any."""
    declared = getattr(request.scope.get("route"), "responses", {}).get(409, {})
    problem_type = declared.get("x-problem-type")
    return problem_type.removeprefix("/problems/") if problem_type else None


def problem_response(request: Request, status: int, title: str, detail: str | None = None, *,
                     slug: str | None = None, errors=None, headers=None, more_errors: int | None = None) -> JSONResponse:
    body = ProblemDetails(type=f"/problems/{slug}" if slug else "about:blank", title=title, status=status, detail=detail,
                          instance=request.url.path, more_errors=more_errors or None,
                          errors=[FieldError(field=f, message=m) for f, m in errors] if errors else None)
    return JSONResponse(body.model_dump(exclude_none=True), status_code=status, media_type=PROBLEM_JSON,
                        headers=headers)


def validation_errors(exc: RequestValidationError, cap: int) -> tuple[list[tuple[str, str]], int]:
    """The first ``cap`` distinct ``(field, message)`` of a validation failure, and how many errors
    were left out. The work is bounded by ``cap`` (plus duplicates), not by the number of errors:
    a body of a million bad items is reported as its first ``cap`` and a count."""
    errors = exc.errors()
    total = getattr(exc, "total", len(errors))
    out: dict[tuple[str, str], None] = {}
    seen = 0
    for err in errors:
        if len(out) >= cap:
            break
        seen += 1
        loc = tuple(err.get("loc", ()))
        if loc and loc[0] in ("body", "query", "path", "header"):
            loc = loc[1:] if loc[0] == "body" else loc
        out[(field_path(loc), err.get("msg", "invalid"))] = None
    return list(out), max(0, total - seen)


def _cap(request: Request) -> int:
    runtime = getattr(request.app.state, "runtime", None)
    return runtime.settings.limits.validation_errors if runtime is not None else 20


def install(app: FastAPI) -> None:
    """The handlers turning errors into problem documents: a route raises the service's own
    exceptions (an unknown job or experiment is a ``404``, a conflict a ``409``) instead of
    catching them itself."""
    @app.exception_handler(UnknownJob)
    async def _unknown_job(request: Request, exc: UnknownJob):
        return problem_response(request, 404, "Not found", f"no job {exc.args[0]!r}", slug="unknown-job")

    @app.exception_handler(UnknownExperiment)
    async def _unknown_experiment(request: Request, exc: UnknownExperiment):
        return problem_response(request, 404, "Not found", f"no experiment {exc.args[0]!r}",
                                slug="unknown-experiment")

    @app.exception_handler(Conflict)
    @app.exception_handler(ExperimentConflict)
    async def _conflict(request: Request, exc: Exception):
        return problem_response(request, 409, "Conflict", str(exc), slug=_conflict_slug(request))

    @app.exception_handler(ProblemError)
    async def _problem(request: Request, exc: ProblemError):
        return problem_response(request, exc.status, exc.title, exc.detail, slug=exc.slug, errors=exc.errors,
                                headers=exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _invalid(request: Request, exc: RequestValidationError):
        errors, more = validation_errors(exc, _cap(request))
        detail = "; ".join(f"{f}: {m}" for f, m in errors[:5])
        if more:
            detail += f" (and {more} more error(s) not listed)"
        return problem_response(request, 422, "Invalid request", detail, slug="invalid-request", errors=errors,
                                more_errors=more)

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException):
        return problem_response(request, exc.status_code, _title(exc.status_code), str(exc.detail),
                                headers=getattr(exc, "headers", None))

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception):
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return problem_response(request, 500, "Internal error", "an unexpected error occurred; it was logged",
                                slug="internal")


def _title(status: int) -> str:
    from http import HTTPStatus

    try:
        return HTTPStatus(status).phrase
    except ValueError:
        return "Error"

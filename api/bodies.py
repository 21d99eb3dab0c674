"""Request bodies read, parsed and validated with bounded work, off the event loop.

A JSON body is first scanned as raw bytes (:func:`check_json`): one pass of a regular expression
over its strings and structural characters, which stops at the first limit it crosses (nesting
depth, keys of an object, items of an array, tokens in all: :class:`services.settings.Limits`).
Only a body within every limit is parsed, and then validated against the route's model, both in a
worker thread. A failed validation keeps its first ``NDRF_MAX_VALIDATION_ERRORS`` errors and the
count of the others, so neither the work nor the response grows with the number of bad items.

:class:`GuardedRoute` is the route class of every ``/v1`` router: it reads the body itself (a body
over the cap is a 413 also when it is chunked, a body that takes too long is a 408), checks and
parses it, and hands FastAPI the validated model, which FastAPI accepts without validating it again.
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Callable, Coroutine
from typing import Any

import anyio
from fastapi import Request, Response
from fastapi.exceptions import RequestValidationError
from fastapi.routing import APIRoute

from api.guard import BodyBusy, BodyTimeout, BodyTooLarge
from api.problems import ProblemError
from services.settings import Limits

log = logging.getLogger(__name__)

#: A JSON string (escapes included) or one structural character; everything else (numbers,
#: literals, whitespace) is skipped by the search.
_TOKEN = re.compile(rb'"[^"\\]*(?:\\.[^"\\]*)*"|[\[\]{},]', re.S)
_QUOTE, _OPEN_LIST, _OPEN_OBJECT, _CLOSE_LIST, _CLOSE_OBJECT = b'"'[0], b"["[0], b"{"[0], b"]"[0], b"}"[0]


class JsonTooComplex(ValueError):
    """A JSON body over one of the structure limits: ``limit`` names the setting, ``position`` is the
    byte offset of the token that crossed it, where the scan stopped (the bytes after it are never
    read)."""

    def __init__(self, limit: str, value: int, what: str, position: int | None = None):
        super().__init__(f"{what} exceeds the limit of {value} (NDRF_MAX_{limit.upper()})")
        self.limit, self.value, self.position = limit, value, position


def check_json(body: bytes, limits: Limits) -> int:
    """Raise :class:`JsonTooComplex` if ``body`` nests deeper than ``json_depth``, has an object of
    more than ``json_keys`` keys, an array of more than ``json_items`` items, or more than
    ``json_tokens`` strings, containers and separators; else return the number of those tokens.
    The work is bounded by the limits, not by the body's size: the scan stops at the first limit
    crossed (the error's ``position``), and a string is one token however long. Invalid JSON is
    left to the parser (the scan over-counts it, never under-counts)."""
    stack: list[list[int]] = []   # per open container: [is_object, entries so far]
    tokens = 0
    for match in _TOKEN.finditer(body):
        at = match.start()
        char = body[at]
        tokens += 1
        if tokens > limits.json_tokens:
            raise JsonTooComplex("json_tokens", limits.json_tokens, "the body's number of JSON tokens (strings, "
                                                                   "arrays, objects and separators)", at)
        if char == _QUOTE:
            continue
        if char in (_OPEN_LIST, _OPEN_OBJECT):
            if len(stack) >= limits.json_depth:
                raise JsonTooComplex("json_depth", limits.json_depth, "the nesting depth of the JSON body", at)
            stack.append([char == _OPEN_OBJECT, 1])
        elif char in (_CLOSE_LIST, _CLOSE_OBJECT):
            if stack:
                stack.pop()
        elif stack:   # a comma: one more entry in the innermost container
            entry = stack[-1]
            entry[1] += 1
            if entry[0] and entry[1] > limits.json_keys:
                raise JsonTooComplex("json_keys", limits.json_keys, "the number of keys of a JSON object", at)
            if not entry[0] and entry[1] > limits.json_items:
                raise JsonTooComplex("json_items", limits.json_items, "the number of items of a JSON array", at)
    return tokens


def parse_json(body: bytes, limits: Limits) -> Any:
    """``json.loads`` of a body within the limits (:func:`check_json` first)."""
    check_json(body, limits)
    return json.loads(body)


def cap_errors(errors: list[Any], total: int, cap: int) -> RequestValidationError:
    """A validation error that keeps the first ``cap`` errors of ``total`` (``.total``), without
    their inputs (a bad item's input can be large)."""
    kept = [{k: v for k, v in err.items() if k not in ("input", "ctx", "url")} for err in errors[:cap]]
    exc = RequestValidationError(kept)
    exc.total = total  # type: ignore[attr-defined]
    return exc


def _is_json(request: Request, strict: bool) -> bool:
    """Whether FastAPI would parse this body as JSON (without a content type: only when not strict)."""
    content_type = request.headers.get("content-type")
    if not content_type:
        return not strict
    media = content_type.split(";", 1)[0].strip().lower()
    return media == "application/json" or (media.startswith("application/") and media.endswith("+json"))


class GuardedRoute(APIRoute):
    """An ``APIRoute`` whose JSON body is read, checked, parsed and validated in bounded work off the
    event loop (see the module's docstring)."""

    def get_route_handler(self) -> Callable[[Request], Coroutine[Any, Any, Response]]:
        handler = super().get_route_handler()
        field = self.body_field
        if field is None:
            return handler
        validate_here = not self._embed_body_fields
        strict = getattr(self, "strict_content_type", True)
        strict = getattr(strict, "value", strict)   # a DefaultPlaceholder unless set

        async def guarded(request: Request) -> Response:
            limits: Limits = request.app.state.runtime.settings.limits
            try:
                body = await request.body()
            except BodyTooLarge as exc:
                raise ProblemError(413, "Payload too large", str(exc), slug="too-large") from None
            except BodyBusy as exc:
                raise ProblemError(503, "Busy", str(exc), slug="busy",
                                   headers={"Retry-After": "5", "Connection": "close"}) from None
            except BodyTimeout as exc:
                raise ProblemError(408, "Request timeout", str(exc), slug="body-timeout",
                                   headers={"Connection": "close"}) from None
            if body and _is_json(request, bool(strict)):
                request._json = await anyio.to_thread.run_sync(self._parse, body, limits, validate_here)
            return await handler(request)

        return guarded

    def _parse(self, body: bytes, limits: Limits, validate: bool) -> Any:
        """In a worker thread: the checked, parsed and (single body model) validated body."""
        try:
            document = parse_json(body, limits)
        except JsonTooComplex as exc:
            log.info("JSON body refused at byte %s of %d: %s", exc.position, len(body), exc)
            raise ProblemError(413, "Body too complex", str(exc), slug="json-limit",
                               errors=[("(root)", str(exc))]) from None
        except (ValueError, RecursionError) as exc:   # JSONDecodeError, and numbers of too many digits
            where = f" at character {exc.pos}" if isinstance(exc, json.JSONDecodeError) else ""
            raise RequestValidationError([{"type": "json_invalid", "loc": ("body",),
                                           "msg": f"JSON decode error{where}: {getattr(exc, 'msg', exc)}"}]) from None
        if not validate or self.body_field is None:
            return document
        value, errors = self.body_field.validate(document, {}, loc=("body",))
        if errors:
            raise cap_errors(list(errors), len(errors), limits.validation_errors)
        return value

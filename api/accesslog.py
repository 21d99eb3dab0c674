"""Keep read tokens out of the access log: uvicorn logs every request's full path, query included.

:class:`RedactTokens` rewrites ``token=<value>`` in a record's arguments (and message) to
``token=REDACTED``, the parameter's name compared after percent-decoding. :func:`install` puts it
on the ``uvicorn.access`` logger of the current process; ``create_app`` calls it, so every API
process (``serve --workers N`` included) has it.
"""

from __future__ import annotations

import logging
import re
from urllib.parse import unquote_plus

#: a query parameter ``name=value`` (after ``?``, ``&`` or ``;``)
_PARAMETER = re.compile(r"((?:^|[?&;])([^=&;?\s\"']+)=)([^&;\s\"']*)")
_SECRET_NAMES = ("token", "access_token")


def _redact_parameter(match: re.Match) -> str:
    name = unquote_plus(match.group(2)).lower()   # ``tok%65n`` is ``token`` to the parser that reads it
    return f"{match.group(1)}REDACTED" if name in _SECRET_NAMES else match.group(0)


def redact(text: str) -> str:
    """``/v1/jobs/j/events?token=abc&after=3`` -> ``/v1/jobs/j/events?token=REDACTED&after=3``; a
    name percent-encoded (``?tok%65n=abc``) is decoded before it is compared."""
    return _PARAMETER.sub(_redact_parameter, text)


class RedactTokens(logging.Filter):
    """Redacts ``token=`` query values in a log record (it never drops a record)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) and "=" in a else a for a in record.args)
        if isinstance(record.msg, str) and "=" in record.msg:
            record.msg = redact(record.msg)
        return True


def install() -> None:
    logger = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactTokens) for f in logger.filters):
        logger.addFilter(RedactTokens())

"""Keep read tokens out of the access log: uvicorn logs every request's full path, query included.

:class:`RedactTokens` rewrites ``token=<value>`` in a record's arguments (and message) to
``token=REDACTED``. :func:`install` puts it on the ``uvicorn.access`` logger of the current
process; ``create_app`` calls it, so every API process (``serve --workers N`` included) has it.
"""

from __future__ import annotations

import logging
import re

_TOKEN = re.compile(r"(?i)((?:^|[?&;])(?:token|access_token)=)[^&\s\"']*")


def redact(text: str) -> str:
    """``/v1/jobs/j/events?token=abc&after=3`` -> ``/v1/jobs/j/events?token=REDACTED&after=3``."""
    return _TOKEN.sub(r"\1REDACTED", text)


class RedactTokens(logging.Filter):
    """Redacts ``token=`` query values in a log record (it never drops a record)."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple):
            record.args = tuple(redact(a) if isinstance(a, str) and "token=" in a.lower() else a
                                for a in record.args)
        if isinstance(record.msg, str) and "token=" in record.msg.lower():
            record.msg = redact(record.msg)
        return True


def install() -> None:
    logger = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactTokens) for f in logger.filters):
        logger.addFilter(RedactTokens())

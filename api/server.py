"""The HTTP protocol ``ndrf serve`` runs: uvicorn's h11 protocol with a header read timeout.

uvicorn has no timeout on reading a request's headers: a client that sends a header line now and
then holds its connection (and a slot of ``limit_concurrency``) forever. :class:`HeaderTimeoutH11`
closes a connection whose request line and headers are not complete within
``NDRF_HEADER_READ_SECONDS`` of the connection opening, or of the end of the previous response on
a keep-alive connection. The body's read time is the app's (``NDRF_BODY_READ_SECONDS``,
:mod:`api.guard`); the header size is h11's (``NDRF_MAX_HEADER_BYTES``).
"""

from __future__ import annotations

import asyncio
import logging

import h11
from uvicorn.protocols.http.h11_impl import H11Protocol

log = logging.getLogger(__name__)

#: uvicorn's ``http=`` import string for this protocol.
PROTOCOL = "api.server:HeaderTimeoutH11"


def _header_seconds() -> float:
    from services.settings import get_settings

    return get_settings().header_read_seconds


class HeaderTimeoutH11(H11Protocol):
    """``H11Protocol`` that closes connections whose headers do not arrive in time (module docstring)."""

    header_timer: asyncio.TimerHandle | None = None
    #: Overrides NDRF_HEADER_READ_SECONDS (tests).
    seconds: float | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._arm()

    def data_received(self, data: bytes) -> None:
        super().data_received(data)
        if self.conn.their_state is not h11.IDLE:   # a request line and its headers are in
            self._disarm()

    def on_response_complete(self) -> None:
        super().on_response_complete()
        if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
            self._arm()   # the next request on this keep-alive connection gets the same time

    def connection_lost(self, exc: Exception | None) -> None:
        self._disarm()
        super().connection_lost(exc)

    def _arm(self) -> None:
        self._disarm()
        self.header_timer = self.loop.call_later(self.seconds or _header_seconds(), self._expired)

    def _disarm(self) -> None:
        if self.header_timer is not None:
            self.header_timer.cancel()
            self.header_timer = None

    def _expired(self) -> None:
        self.header_timer = None
        if self.conn.their_state is h11.IDLE and not self.transport.is_closing():
            log.info("closing a connection from %s: no complete request headers within %g s "
                     "(NDRF_HEADER_READ_SECONDS)", self.client, self.seconds or _header_seconds())
            self.transport.close()

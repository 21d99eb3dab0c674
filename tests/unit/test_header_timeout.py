"""The header read timeout of ``ndrf serve``'s protocol (api.server): a connection whose headers do
not arrive in time is closed, also when it trickles header lines and on a keep-alive connection
after its first response; a prompt request is answered as usual."""

from __future__ import annotations

import socket
import threading
import time

import pytest
import uvicorn

from api.server import HeaderTimeoutH11
from harness.cluster import free_port


class Quick(HeaderTimeoutH11):
    seconds = 0.5


async def app(scope, receive, send):
    if scope["type"] != "http":
        return
    await send({"type": "http.response.start", "status": 200, "headers": [(b"content-length", b"2")]})
    await send({"type": "http.response.body", "body": b"ok"})


@pytest.fixture(scope="module")
def port():
    port = free_port()
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=port, http=Quick, log_level="warning",
                                           timeout_keep_alive=30, lifespan="off"))
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 10
    while not server.started and time.monotonic() < deadline:
        time.sleep(0.02)
    yield port
    server.should_exit = True
    thread.join(10)


def closed_within(sock: socket.socket, seconds: float, trickle: bool = False) -> bool:
    deadline = time.monotonic() + seconds
    sock.settimeout(0.1)
    while time.monotonic() < deadline:
        try:
            if trickle:
                sock.sendall(b"X-Slow: 1\r\n")
            data = sock.recv(4096)
            if data == b"":
                return True
        except TimeoutError:
            continue
        except (ConnectionError, BrokenPipeError):
            return True
    return False


def test_trickled_headers_are_cut(port):
    with socket.create_connection(("127.0.0.1", port)) as sock:
        sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n")
        assert closed_within(sock, 2.0, trickle=True)


def test_a_prompt_request_is_answered_and_the_next_one_is_timed_too(port):
    with socket.create_connection(("127.0.0.1", port)) as sock:
        time.sleep(0.3)
        sock.sendall(b"GET / HTTP/1.1\r\nHost: x\r\n\r\n")
        sock.settimeout(2)
        assert sock.recv(4096).startswith(b"HTTP/1.1 200")
        sock.sendall(b"GET / HTTP/1.1\r\n")        # keep-alive: a second request that never completes
        assert closed_within(sock, 2.0)

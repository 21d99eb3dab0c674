"""The measuring side of the adversarial suite (tests/e2e/test_adversarial.py): raw HTTP requests whose
body is sent while the response is read (a server may answer before reading it), a sampler of a
process's resident memory, a ``/healthz`` prober, and the table of what each attack cost."""

from __future__ import annotations

import http.client
import json
import logging
import socket
import threading
import time
import urllib.request
from collections.abc import Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path

log = logging.getLogger(__name__)


def rss_mib(pid: int, key: str = "VmRSS") -> float:
    """A line of /proc/<pid>/status in MiB (VmRSS: now; VmHWM: the peak so far)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) / 1024
    raise KeyError(key)


@dataclass
class Outcome:
    attack: str
    status: int
    seconds: float
    peak_mib_above_idle: float = 0.0
    start_mib_above_idle: float = 0.0
    healthz_max_seconds: float = 0.0
    healthz_probes: int = 0
    note: str = ""
    extra: dict = field(default_factory=dict)


class Watch:
    """While open: the API's resident memory sampled every 10 ms and ``/healthz`` probed every 100 ms
    (each probe's latency; a probe that fails counts as its timeout)."""

    def __init__(self, pid: int, base: str, idle_mib: float):
        self.pid, self.base, self.idle = pid, base, idle_mib
        self.peak = self.start = rss_mib(pid)
        self.latencies: list[float] = []
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._sample, daemon=True),
                         threading.Thread(target=self._probe, daemon=True)]

    def __enter__(self) -> Watch:
        for thread in self._threads:
            thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(10)

    def _sample(self) -> None:
        while not self._stop.is_set():
            self.peak = max(self.peak, rss_mib(self.pid))
            time.sleep(0.01)

    def _probe(self) -> None:
        while not self._stop.is_set():
            started = time.monotonic()
            try:
                with urllib.request.urlopen(self.base + "/healthz", timeout=5) as resp:
                    resp.read()
                self.latencies.append(time.monotonic() - started)
            except OSError:
                self.latencies.append(5.0)
            self._stop.wait(0.1)

    def outcome(self, attack: str, status: int, seconds: float, note: str = "", **extra) -> Outcome:
        return Outcome(attack, status, round(seconds, 3), round(max(0.0, self.peak - self.idle), 1),
                       round(self.start - self.idle, 1), round(max(self.latencies, default=0.0), 3),
                       len(self.latencies), note, extra)


def raw_request(port: int, method: str, path: str, headers: dict[str, str], body: Iterable[bytes] = (),
                timeout: float = 60) -> tuple[int, dict[str, str], bytes]:
    """Send a request line and headers, then ``body`` from a thread while the response is read:
    an answer that comes before the body is read (401, 413) is seen, and the rest of the body then
    fails to send (ignored)."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=timeout)
    if not any(k.lower() == "host" for k in headers):
        headers = {"Host": f"127.0.0.1:{port}", **headers}
    head = f"{method} {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in headers.items()) + "\r\n"
    sock.sendall(head.encode("latin-1"))

    def pump() -> None:
        try:
            for chunk in body:
                sock.sendall(chunk)
        except OSError:
            pass

    sender = threading.Thread(target=pump, daemon=True)
    sender.start()
    try:
        response = http.client.HTTPResponse(sock)
        response.begin()
        data = response.read()
        return response.status, {k.lower(): v for k, v in response.getheaders()}, data
    finally:
        sock.close()
        sender.join(timeout)


def chunked(total: int, piece: int = 1 << 20, byte: bytes = b" ") -> Iterable[bytes]:
    """``total`` bytes in HTTP/1.1 chunked encoding."""
    sent = 0
    while sent < total:
        size = min(piece, total - sent)
        yield f"{size:x}\r\n".encode() + byte * size + b"\r\n"
        sent += size
    yield b"0\r\n\r\n"


def pieces(data: bytes, piece: int = 1 << 20) -> Iterable[bytes]:
    for start in range(0, len(data), piece):
        yield data[start:start + piece]


def report(outcomes: list[Outcome], path: Path) -> str:
    """Write the outcomes as JSON to ``path``; returns them as a text table (also logged)."""
    path.write_text(json.dumps([asdict(o) for o in outcomes], indent=2))
    lines = ["peak and start: the API's resident memory above its idle size, in MiB (RSS does not shrink back "
             "after an attack, so start is what earlier attacks left)",
             f"{'attack':34} {'status':>6} {'seconds':>8} {'peak':>7} {'start':>7} {'healthz max s':>13}  note",
             *(f"{o.attack:34} {o.status:>6} {o.seconds:>8.3f} {o.peak_mib_above_idle:>7.1f} "
               f"{o.start_mib_above_idle:>7.1f} {o.healthz_max_seconds:>13.3f}  {o.note}" for o in outcomes)]
    table = "\n".join(lines)
    log.warning("adversarial suite (%s):\n%s", path, table)
    return table

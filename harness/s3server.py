"""A real S3 HTTP endpoint on loopback for the tests and the store benchmark: moto's server mode,
in a child process (``python -m harness.s3server``), so the API, the workers and the test process
all talk to it over HTTP as they would to a bucket on another machine.

Moto (5.2) honours ``If-None-Match: *`` and ``If-Match: <etag>`` on PutObject, but checks the
condition and stores the object in two steps without a lock (``S3Response.put_object``): two
concurrent conditional PUTs can in principle both pass the check. S3 itself documents conditional
writes as atomic, and that is what the store relies on. The child therefore serialises moto's
PutObject handler behind one lock (``--stock`` runs moto unchanged): the tests then exercise our
client's conditional path against a server with S3's semantics, not against a lucky interleaving.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]  # the checkout
ACCESS_KEY, SECRET_KEY, REGION = "ndrf-test", "ndrf-test-secret", "us-east-1"


def make_conditional_puts_atomic() -> None:
    """One lock around moto's PutObject handler: the precondition check and the write become one step."""
    from moto.s3.responses import S3Response

    lock = threading.Lock()
    put_object = S3Response.put_object

    def atomic_put_object(self):
        with lock:
            return put_object(self)

    S3Response.put_object = atomic_put_object  # type: ignore[method-assign]


def serve(port: int, buckets: list[str], stock: bool) -> None:
    from moto.server import ThreadedMotoServer

    if not stock:
        make_conditional_puts_atomic()
    server = ThreadedMotoServer(ip_address="127.0.0.1", port=port, verbose=False)
    server.start()
    host, bound = server.get_host_and_port()
    endpoint = f"http://{host}:{bound}"
    import boto3

    client = boto3.client("s3", endpoint_url=endpoint, region_name=REGION, aws_access_key_id=ACCESS_KEY,
                          aws_secret_access_key=SECRET_KEY)
    for bucket in buckets:
        client.create_bucket(Bucket=bucket)
    print(f"READY {endpoint}", flush=True)
    try:
        while sys.stdin.read(1):  # until the parent closes our stdin (or dies)
            pass
    finally:
        server.stop()


class S3Server:
    """``python -m harness.s3server`` as a child process; ``env(bucket, prefix)`` is what a process
    of the service needs to use it (``NDRF_STORE``, ``NDRF_S3_ENDPOINT``, AWS credentials)."""

    def __init__(self, buckets: tuple[str, ...] = ("ndrf",), stock: bool = False):
        self.buckets, self.stock = buckets, stock
        self.proc: subprocess.Popen | None = None
        self.endpoint = ""

    def start(self, timeout: float = 60.0) -> S3Server:
        args = [sys.executable, "-m", "harness.s3server", "--bucket", *self.buckets,
                *(["--stock"] if self.stock else [])]
        self.proc = subprocess.Popen(args, cwd=ROOT, stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                                     stderr=subprocess.DEVNULL, text=True)
        deadline = time.monotonic() + timeout
        assert self.proc.stdout is not None
        while time.monotonic() < deadline:
            line = self.proc.stdout.readline()
            if line.startswith("READY "):
                self.endpoint = line.split()[1]
                return self
            if not line and self.proc.poll() is not None:
                break
        self.stop()
        raise RuntimeError("the moto S3 server did not start (is moto[server] installed? pip install -e '.[dev]')")

    def env(self, bucket: str = "ndrf", prefix: str = "") -> dict[str, str]:
        return {"NDRF_STORE": f"s3://{bucket}/{prefix}", "NDRF_S3_ENDPOINT": self.endpoint,
                "AWS_ACCESS_KEY_ID": ACCESS_KEY, "AWS_SECRET_ACCESS_KEY": SECRET_KEY, "AWS_REGION": REGION}

    def stop(self) -> None:
        if self.proc is not None:
            if self.proc.stdin:
                self.proc.stdin.close()
            try:
                self.proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
            self.proc = None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--port", type=int, default=0)
    parser.add_argument("--bucket", nargs="*", default=["ndrf"])
    parser.add_argument("--stock", action="store_true", help="moto unchanged (conditional PUTs not serialised)")
    args = parser.parse_args()
    os.environ.setdefault("MOTO_ALLOW_NONEXISTENT_REGION", "true")
    serve(args.port, args.bucket, args.stock)


if __name__ == "__main__":
    main()

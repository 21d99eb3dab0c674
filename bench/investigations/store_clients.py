"""``python -m bench.investigations.store_clients``: which S3 client the store uses, measured.

Per-operation latency (median and 90th percentile of ``--reps`` calls) of obstore, boto3 and
s3fs against the same moto server on loopback (``harness/s3server.py``, a child process), for the
operations the store makes: PUT 1 KiB (a record), PUT 1 MiB (an image stack), conditional create
(``If-None-Match: *``), GET 1 KiB, GET 1 MiB, HEAD, LIST of 200 keys. Also the import time of each
client in a fresh interpreter and the installed size of its dependency closure. A client that is
not installed is skipped. Loopback moto measures client overhead, not a real network.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
log = logging.getLogger("bench.investigations.store_clients")
KIB = b"k" * 1024
MIB = b"m" * (1 << 20)


def _server() -> tuple[subprocess.Popen, str]:
    proc = subprocess.Popen([sys.executable, "-m", "harness.s3server", "--bucket", "bench"], cwd=ROOT,
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    assert proc.stdout is not None
    line = proc.stdout.readline()
    if not line.startswith("READY "):
        raise RuntimeError("moto server did not start")
    return proc, line.split()[1]


CREDS = {"key": "ndrf-test", "secret": "ndrf-test-secret", "region": "us-east-1"}


def obstore_ops(endpoint: str) -> dict[str, Callable[[int], object]]:
    import obstore
    from obstore.store import S3Store

    store = S3Store("bench", prefix="obstore", endpoint=endpoint, region=CREDS["region"],
                    access_key_id=CREDS["key"], secret_access_key=CREDS["secret"], client_options={"allow_http": True})
    return {
        "put 1 KiB": lambda i: obstore.put(store, f"small/{i}", KIB),
        "put 1 MiB": lambda i: obstore.put(store, f"large/{i}", MIB),
        "create (If-None-Match)": lambda i: obstore.put(store, f"create/{i}", KIB, mode="create"),
        "get 1 KiB": lambda i: obstore.get(store, "small/0").bytes(),
        "get 1 MiB": lambda i: obstore.get(store, "large/0").bytes(),
        "head": lambda i: obstore.head(store, "small/0"),
        "list 200 keys": lambda i: obstore.list(store, prefix="list").collect(),
        "_seed": lambda i: obstore.put(store, f"list/{i:04d}", b"x"),
    }


def boto3_ops(endpoint: str) -> dict[str, Callable[[int], object]]:
    import boto3

    s3 = boto3.client("s3", endpoint_url=endpoint, region_name=CREDS["region"], aws_access_key_id=CREDS["key"],
                      aws_secret_access_key=CREDS["secret"])

    def listing(i):
        return [o["Key"] for page in s3.get_paginator("list_objects_v2").paginate(Bucket="bench", Prefix="boto3/list/")
                for o in page.get("Contents", [])]

    return {
        "put 1 KiB": lambda i: s3.put_object(Bucket="bench", Key=f"boto3/small/{i}", Body=KIB),
        "put 1 MiB": lambda i: s3.put_object(Bucket="bench", Key=f"boto3/large/{i}", Body=MIB),
        "create (If-None-Match)": lambda i: s3.put_object(Bucket="bench", Key=f"boto3/create/{i}", Body=KIB,
                                                          IfNoneMatch="*"),
        "get 1 KiB": lambda i: s3.get_object(Bucket="bench", Key="boto3/small/0")["Body"].read(),
        "get 1 MiB": lambda i: s3.get_object(Bucket="bench", Key="boto3/large/0")["Body"].read(),
        "head": lambda i: s3.head_object(Bucket="bench", Key="boto3/small/0"),
        "list 200 keys": listing,
        "_seed": lambda i: s3.put_object(Bucket="bench", Key=f"boto3/list/{i:04d}", Body=b"x"),
    }


def s3fs_ops(endpoint: str) -> dict[str, Callable[[int], object]]:
    import s3fs

    fs = s3fs.S3FileSystem(key=CREDS["key"], secret=CREDS["secret"], endpoint_url=endpoint,
                           client_kwargs={"region_name": CREDS["region"]}, use_listings_cache=False)
    base = "bench/s3fs"
    return {
        "put 1 KiB": lambda i: fs.pipe_file(f"{base}/small/{i}", KIB),
        "put 1 MiB": lambda i: fs.pipe_file(f"{base}/large/{i}", MIB),
        "create (If-None-Match)": lambda i: fs.pipe_file(f"{base}/create/{i}", KIB, mode="create"),
        "get 1 KiB": lambda i: fs.cat_file(f"{base}/small/0"),
        "get 1 MiB": lambda i: fs.cat_file(f"{base}/large/0"),
        "head": lambda i: fs.info(f"{base}/small/0"),
        "list 200 keys": lambda i: fs.find(f"{base}/list/"),
        "_seed": lambda i: fs.pipe_file(f"{base}/list/{i:04d}", b"x"),
    }


CLIENTS = {"obstore": (obstore_ops, "obstore"), "boto3": (boto3_ops, "boto3"), "s3fs": (s3fs_ops, "s3fs")}


def closure_bytes(dist: str) -> tuple[int, list[str]]:
    """Installed bytes of a distribution and everything it requires (no extras)."""
    from packaging.requirements import Requirement

    seen: set[str] = set()
    todo = [dist]
    total = 0
    while todo:
        name = todo.pop().lower().replace("_", "-")
        if name in seen:
            continue
        seen.add(name)
        try:
            d = metadata.distribution(name)
        except metadata.PackageNotFoundError:
            continue
        total += sum((f.size or 0) for f in (d.files or []))
        for raw in d.requires or []:
            req = Requirement(raw)
            if req.marker is None or req.marker.evaluate({"extra": ""}):
                todo.append(req.name)
    return total, sorted(seen)


def import_seconds(module: str) -> float:
    runs = []
    for _ in range(3):
        start = time.perf_counter()
        subprocess.run([sys.executable, "-c", f"import {module}"], check=True)
        runs.append(time.perf_counter() - start)
    base = min(_python_startup() for _ in range(3))
    return max(0.0, min(runs) - base)


def _python_startup() -> float:
    start = time.perf_counter()
    subprocess.run([sys.executable, "-c", "pass"], check=True)
    return time.perf_counter() - start


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.store_clients", description=__doc__)
    parser.add_argument("--reps", type=int, default=100)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "store_clients.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    proc, endpoint = _server()
    results: dict = {"endpoint": "moto (harness/s3server.py) on loopback", "reps": args.reps, "clients": {}}
    try:
        for name, (factory, dist) in CLIENTS.items():
            try:
                ops = factory(endpoint)
            except ImportError:
                log.info("%s: not installed, skipped", name)
                continue
            for i in range(200):
                ops["_seed"](i)
            row: dict = {}
            for op, call in ops.items():
                if op.startswith("_"):
                    continue
                call(0)  # warm-up (connection, first object)
                times = []
                for i in range(1, args.reps + 1):
                    start = time.perf_counter()
                    call(i)
                    times.append(time.perf_counter() - start)
                times.sort()
                row[op] = {"median_ms": 1000 * statistics.median(times), "p90_ms": 1000 * times[int(0.9 * len(times))]}
            size, deps = closure_bytes(dist)
            results["clients"][name] = {"ops": row, "import_s": import_seconds(name), "installed_mib": size / 2**20,
                                        "distributions": deps}
    finally:
        if proc.stdin:
            proc.stdin.close()
        proc.wait(timeout=10)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    ops = list(next(iter(results["clients"].values()))["ops"])
    lines = ["| client | " + " | ".join(ops) + " | import s | installed MiB (closure) |", "|---" * (len(ops) + 3) + "|"]
    for name, r in results["clients"].items():
        cells = [f"{r['ops'][op]['median_ms']:.2f} ({r['ops'][op]['p90_ms']:.2f})" for op in ops]
        lines.append(f"| {name} | " + " | ".join(cells) + f" | {r['import_s']:.2f} | {r['installed_mib']:.1f} "
                     f"({len(r['distributions'])} dists) |")
    log.info("%s", "\n".join(lines))


if __name__ == "__main__":
    main()

"""``python -m bench.store_overhead``: what writing a job's artifacts costs per iteration, in the
folder store and in the S3 store, so a user knows what going multi-machine costs.

One realistic iteration as the worker's :class:`services.jobs.artifacts.JobWriter` writes it (the
same code the service runs): the render PNG, the gradient stack ``.npy`` (P scalars x H x W x 3
float32) and one PNG preview per scalar, the iteration record, the fenced compare-and-set of the
job record, the ``iteration`` event; and every ``--checkpoint-every`` iterations a checkpoint
(default 8,737,078 bytes: the size of ``checkpoints/latest.pt`` that ``ndrf run`` wrote for a
cornell-box job with the default field configuration) with its info file and event.

Reported per iteration: wall seconds (median and mean over ``--iterations``, checkpoints
included in the mean), the same work with a store that discards everything (PNG encoding and
record handling alone: the store's own share is the difference), bytes written (what crosses the
network to a bucket; the checkpoint is overwritten, so less is kept) and, for S3, HTTP requests.
The S3 store talks to moto on loopback (``harness/s3server.py``) unless ``--endpoint`` names a real
server (credentials from the AWS environment variables; ``--bucket``): on a network,
add requests x round-trip time.
"""

from __future__ import annotations

import argparse
import json
import logging
import statistics
import subprocess
import sys
import tempfile
import time
import uuid
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
CHECKPOINT_BYTES = 8_737_078


def _image(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """A render-like image: smooth shading plus Monte Carlo noise (compresses like a real one)."""
    y, x = np.mgrid[0:h, 0:w] / max(h, w)
    base = np.stack([0.6 * (1 - y), 0.4 + 0.2 * x, 0.3 + 0.3 * x * y], -1)
    return np.clip(base * (1 + 0.15 * rng.standard_normal((h, w, 3))), 0, None).astype(np.float32)


def _record(k: int, p: int):
    from schemas.records import IterationRecord

    return IterationRecord(iteration=k, loss=0.01 / (k + 1), parameters=[0.3] * p, updated_parameters=[0.31] * p,
                           dz_dp=[0.001] * p, learning_rate=0.05, seconds={"training": 1.0, "rendering": 0.1},
                           training_steps=8, images=True)


class _Discard:
    """An in-memory stand-in with the store's calls that keeps only the job record: the cost of
    the writer's own work (encoding, records, events) without any storage."""

    def __new__(cls):
        from services.store.base import ArtifactStore

        class Discard(ArtifactStore):
            def __init__(self):
                self.objects: dict[str, bytes] = {}
                self.seq: Counter[str] = Counter()

            def get(self, key):
                return self.objects.get(key)

            def put(self, key, data, *, durable=True):
                if key.endswith("record.json") and "/iterations/" not in key:
                    self.objects[key] = data

            def get_versioned(self, key):
                data = self.objects.get(key)
                return None if data is None else (data, str(hash(data)))

            def put_if(self, key, data, version):
                self.objects[key] = data
                return str(hash(data))

            def exists(self, key):
                return key in self.objects

            def size(self, key):
                return len(self.objects[key]) if key in self.objects else None

            def keys(self, prefix, *, delimiter=False):
                return iter(sorted(k for k in self.objects if k.startswith(prefix)))

            def delete_prefix(self, prefix):
                return 0

            def open(self, key):
                return None

            def usage_bytes(self):
                return 0

            def append_event(self, prefix, event, *, durable=True):
                self.seq[prefix] += 1
                return {"seq": self.seq[prefix], **event}

            def read_events(self, prefix, after=0, cursor=None):
                return [], cursor

        return Discard()


def _count_requests(counter: Counter) -> None:
    """Count the HTTP requests the S3 store makes (one per obstore call; one per page of a list)."""
    import obstore

    import services.store.s3 as s3

    class Counting:
        def __getattr__(self, name):
            real = getattr(obstore, name)
            if name == "list":
                def listing(*args, **kwargs):
                    for page in real(*args, **kwargs):
                        counter["list"] += 1
                        yield page
                return listing

            def call(*args, **kwargs):
                counter[name] += 1
                return real(*args, **kwargs)
            return call

    s3.obstore = Counting()  # type: ignore[assignment]


def _count_written(store: Any) -> Counter:
    """Bytes handed to the store (puts, compare-and-sets, events), counted on the instance."""
    from services.store.files import dumps
    from services.store.local import FolderStore

    written: Counter = Counter()
    put, put_if, append = store.put, store.put_if, store.append_event

    def counting_put(key, data, *, durable=True):
        written["bytes"] += len(data)
        return put(key, data, durable=durable)

    def counting_put_if(key, data, version):
        written["bytes"] += len(data)
        return put_if(key, data, version)

    def counting_append(prefix, event, *, durable=True):
        stored = append(prefix, event, durable=durable)
        if isinstance(store, FolderStore):       # the S3 store's events are counted as its put_if
            written["bytes"] += len(dumps(stored, indent=None)) + 1
        return stored

    store.put, store.put_if, store.append_event = counting_put, counting_put_if, counting_append
    return written


def run_store(store: Any, args, counter: Counter | None) -> dict:
    from schemas.records import JobRecord, JobStatus
    from services.jobs.artifacts import JobWriter
    from services.jobs.state import JobStates, now_iso

    rng = np.random.default_rng(0)
    h, w = args.resolution
    render = _image(rng, h, w)
    gradients = (rng.standard_normal((args.scalars, h, w, 3)) * 0.01).astype(np.float32)
    checkpoint = rng.integers(0, 256, args.checkpoint_bytes, dtype=np.uint8).tobytes()
    states = JobStates(store)
    job_id = f"{int(time.time() * 1000):012x}{uuid.uuid4().hex[:8]}"
    now = now_iso()
    states.create(JobRecord(id=job_id, status=JobStatus.QUEUED, method="ndrf-rhs", scene="cornell-box", created=now,
                            updated=now, iterations=args.iterations))
    states.transition(job_id, JobStatus.RUNNING, attempt="bench#1")
    writer = JobWriter(states, job_id, attempt="bench#1", byte_budget=None)
    before = store.prefix_bytes(f"{job_id}/")
    written = _count_written(store)
    if counter is not None:
        counter.clear()
    seconds, checkpoints = [], []
    for k in range(args.iterations):
        start = time.perf_counter()
        writer.iteration(_record(k, args.scalars), {0: render}, {0: gradients})
        if (k + 1) % args.checkpoint_every == 0:
            cp = time.perf_counter()
            writer.checkpoint(checkpoint, k + 1)
            checkpoints.append(time.perf_counter() - cp)
        seconds.append(time.perf_counter() - start)
    requests = sum(counter.values()) if counter is not None else None
    kinds = dict(counter) if counter is not None else None
    stored = store.prefix_bytes(f"{job_id}/") - before
    return {"median_s": statistics.median(seconds), "mean_s": statistics.mean(seconds),
            "checkpoint_s": statistics.mean(checkpoints) if checkpoints else None,
            "written_bytes_per_iteration": written["bytes"] / args.iterations,
            "stored_bytes_per_iteration": stored / args.iterations,
            "requests_per_iteration": None if requests is None else requests / args.iterations,
            "requests_by_kind": kinds}


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.store_overhead", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--iterations", type=int, default=40)
    parser.add_argument("--resolution", type=int, nargs=2, default=[128, 128], metavar=("H", "W"))
    parser.add_argument("--scalars", type=int, default=3, help="P: optimized scalars (one RGB parameter = 3)")
    parser.add_argument("--checkpoint-every", type=int, default=10, help="the job spec's default")
    parser.add_argument("--checkpoint-bytes", type=int, default=CHECKPOINT_BYTES)
    parser.add_argument("--endpoint", default=None, help="a real S3 endpoint (default: moto on loopback)")
    parser.add_argument("--bucket", default="bench")
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "store_overhead.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")

    from services.store.local import FolderStore
    from services.store.s3 import S3Store

    results: dict = {"config": {k: v for k, v in vars(args).items() if k != "out"}}
    results["config"]["out"] = str(args.out)
    results["discard"] = run_store(_Discard(), args, None)
    with tempfile.TemporaryDirectory(prefix="ndrf-bench-store-") as tmp:
        results["folder"] = run_store(FolderStore(tmp), args, None)
    proc = None
    try:
        if args.endpoint:
            endpoint, extra = args.endpoint, {}
        else:
            proc = subprocess.Popen([sys.executable, "-m", "harness.s3server", "--bucket", args.bucket], cwd=ROOT,
                                    stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
            assert proc.stdout is not None
            line = proc.stdout.readline()
            if not line.startswith("READY "):
                raise RuntimeError("the moto S3 server did not start")
            endpoint = line.split()[1]
            extra = {"access_key_id": "ndrf-test", "secret_access_key": "ndrf-test-secret", "region": "us-east-1"}
        counter: Counter = Counter()
        _count_requests(counter)
        store = S3Store(f"s3://{args.bucket}/bench-{uuid.uuid4().hex[:8]}", endpoint=endpoint, **extra)
        results["s3"] = run_store(store, args, counter)
        results["s3"]["endpoint"] = args.endpoint or "moto (harness/s3server.py) on loopback"
    finally:
        if proc is not None and proc.stdin:
            proc.stdin.close()
            proc.wait(timeout=10)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    lines = [f"{args.iterations} iterations, {args.resolution[0]}x{args.resolution[1]}, P={args.scalars}, checkpoint "
             f"{args.checkpoint_bytes / 2**20:.1f} MiB every {args.checkpoint_every}",
             "| store | median s/iter | mean s/iter (with checkpoints) | checkpoint s | store share of mean | "
             "bytes written/iter | bytes kept/iter | requests/iter |",
             "|---|---|---|---|---|---|---|---|"]
    base = results["discard"]["mean_s"]
    for name in ("discard", "folder", "s3"):
        r = results[name]
        cp = f"{r['checkpoint_s']:.3f}" if r["checkpoint_s"] is not None else "-"
        req = f"{r['requests_per_iteration']:.1f}" if r["requests_per_iteration"] is not None else "-"
        lines.append(f"| {name} | {r['median_s']:.4f} | {r['mean_s']:.4f} | {cp} | {r['mean_s'] - base:+.4f} | "
                     f"{r['written_bytes_per_iteration']:,.0f} | {r['stored_bytes_per_iteration']:,.0f} | {req} |")
    lines.append(f"requests by kind (s3, whole run): {results['s3']['requests_by_kind']}")
    logging.getLogger("bench.store_overhead").info("\n%s", "\n".join(lines))


if __name__ == "__main__":
    main()

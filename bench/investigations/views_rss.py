"""The API's resident memory around views (issue 38: a 512x512 view's arrays took the API from 87
to 1595 MiB when they came back to it): a real ``ndrf serve`` (embedded), a one-iteration small
job, then three 256x256 views at 16 spp with ``prb_spp`` 16 (the third ``inline``), the API's
VmRSS sampled every 10 ms during each.

    python -m bench.investigations.views_rss
"""

from __future__ import annotations

import json
import logging
import tempfile
import threading
import time
from pathlib import Path

from harness.cluster import small_job, start_api

log = logging.getLogger("bench.investigations.views_rss")


def rss_mib(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    raise KeyError("VmRSS")


def main() -> None:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        proc, api = start_api(folder, {"NDRF_STORE": str(folder / "store"), "NDRF_API_KEYS": "alice"})
        try:
            status, _, job = api.json("POST", "/v1/jobs", small_job("ndrf-lhs", iterations=1))
            assert status == 202, job
            api.wait_status(job["id"], ("succeeded",), 600)
            for i, inline in enumerate((False, False, True)):
                time.sleep(1.0)
                before = rss_mib(proc.pid)
                peak, done = [before], threading.Event()

                def sample(peak=peak, done=done):
                    while not done.is_set():
                        peak[0] = max(peak[0], rss_mib(proc.pid))
                        time.sleep(0.01)

                sampler = threading.Thread(target=sample)
                sampler.start()
                body = {"origin": [0.3 - 0.1 * i, 0.2, 3.0], "target": [0, 0, 0], "resolution": [256, 256],
                        "spp": 16, "prb_spp": 16, "inline": inline}
                status, _, _ = api.request("POST", f"/v1/jobs/{job['id']}/views", body, timeout=600)
                done.set()
                sampler.join()
                row = {"view": i, "inline": inline, "status": status, "rss_before_mib": round(before, 1),
                       "peak_rise_mib": round(peak[0] - before, 1), "rss_after_mib": round(rss_mib(proc.pid), 1)}
                log.info("%s", json.dumps(row))
        finally:
            proc.kill()


if __name__ == "__main__":
    main()

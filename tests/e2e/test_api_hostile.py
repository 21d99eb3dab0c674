"""Hostile uploads against a real ``ndrf serve`` and a real ``ndrf worker`` (Redis mode): each
attack of issue 13 is a 4xx problem naming its cause (or a failed job naming it), and afterwards
the API and the worker still answer and a normal job still finishes. The API process's peak
memory stays below a bound: it never loads a scene itself (children do)."""

from __future__ import annotations

import base64
import json
import math
import signal
import struct

import pytest

from harness.cluster import Process, Redis, small_job, start_api
from tests.support.payloads import QUAD, TRIANGLES, ply_header, png, serialized, serialized_shape
from tests.support.scenes import SELF_CONTAINED_XML, upload_scene

#: The API process's peak resident memory after the whole suite (VmHWM), in MiB. The API imports
#: FastAPI, pydantic, numpy and Pillow; a scene loaded in-process would add Mitsuba (and a hostile
#: one arbitrarily more).
API_PEAK_MIB = 300


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode()


def scene_job(xml: str, files: dict[str, bytes] | None = None, **extra) -> dict:
    job = small_job("direct", iterations=2)
    job.update(scene={"xml": xml, "files": {k: b64(v) for k, v in (files or {}).items()}},
               parameters=[{"key": "paint.reflectance.value", "init": 0.5}],
               targets={"synthetic": {"values": {"paint.reflectance.value": [0.3, 0.4, 0.5]}, "spp": 4}},
               render={"spp": 2, "gradient_spp": 2})
    job.update(extra)
    return job


def with_shapes(body: str) -> str:
    return SELF_CONTAINED_XML.replace("</scene>", body + "</scene>")


@pytest.fixture(scope="module")
def service(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("hostile")
    redis = Redis().start()
    env = {"REDIS_URL": redis.url, "NDRF_STORE": str(tmp / "store"), "NDRF_LEASE_SECONDS": "5"}
    api_proc, api = start_api(tmp, env)
    worker = Process(["-v", "worker", "--name", "w"], env, tmp / "worker.log")
    yield api, api_proc, worker, env
    for proc in (worker, api_proc):
        proc.kill(signal.SIGKILL)
    redis.kill()


def refused(api, job, field: str, *fragments: str, status: int = 422) -> dict:
    code, headers, problem = api.json("POST", "/v1/jobs", job)
    assert code == status, problem
    assert headers["content-type"] == "application/problem+json"
    fields = [e["field"] for e in problem.get("errors", [])]
    assert field in fields, (fields, problem)
    for fragment in fragments:
        assert fragment in problem["detail"], (fragment, problem["detail"])
    return problem


ATTACKS = {
    "PLY vertex count past 32 bits": lambda: scene_job(
        with_shapes('<shape type="ply"><string name="filename" value="m.ply"/><ref id="paint"/></shape>'),
        {"m.ply": ply_header("binary_little_endian", 4294967297, 1) + struct.pack("<3f", 0, 0, 0) * 4000}),
    "20,000 nested BSDFs": lambda: scene_job(
        with_shapes('<bsdf type="twosided" id="deep">' * 1 + '<bsdf type="twosided">' * 20000
                    + '<bsdf type="diffuse"/>' + "</bsdf>" * 20001)),
    "one fragment included 1,000 times": lambda: scene_job(
        with_shapes('<include filename="f.xml"/>' * 1000),
        {"f.xml": ('<scene version="3.0.0">' + '<integer name="x" value="1"/>' * 200 + "</scene>").encode()}),
    "one mesh referenced 50,000 times": lambda: scene_job(
        with_shapes('<shape type="obj"><string name="filename" value="q.obj"/><ref id="paint"/></shape>' * 50000),
        {"q.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"}),
    "one 1 MB mesh referenced 300 times": lambda: scene_job(
        with_shapes('<shape type="obj"><string name="filename" value="big.obj"/><ref id="paint"/></shape>' * 300),
        {"big.obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n" + b"# padding\n" * 100_000}),
    "a zlib bomb in a serialized mesh": lambda: scene_job(
        with_shapes('<shape type="serialized"><string name="filename" value="b.serialized"/><ref id="paint"/></shape>'),
        {"b.serialized": serialized(serialized_shape(QUAD[:0], TRIANGLES[:0], flags=0x2000 | 0x1 | 0x2 | 0x8,
                                                     vertices=10_000_000, faces=1, tail=bytes(8 << 20)))}),
    "an overlong UTF-8 file name": lambda: scene_job(
        with_shapes('<shape type="obj"><string name="filename" value="' + "é" * 200 + '.obj"/></shape>'),
        {"é" * 200 + ".obj": b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n"}),
}
EXPECTED = {
    "PLY vertex count past 32 bits": ("scene.files[m.ply]", "4294967297"),
    "20,000 nested BSDFs": ("scene.xml", "max_xml_depth"),
    "one fragment included 1,000 times": ("scene.files[f.xml]", "included 1000 times"),
    "one mesh referenced 50,000 times": ("scene.xml", "max_xml_elements"),
    "one 1 MB mesh referenced 300 times": ("scene.files[big.obj]", "max_referenced_bytes"),
    "a zlib bomb in a serialized mesh": ("scene.files[b.serialized]", "max_mesh_decompressed_bytes"),
    "an overlong UTF-8 file name": ("scene.files[" + "é" * 200 + ".obj]", "bytes"),
}


@pytest.mark.parametrize("attack", list(ATTACKS))
def test_a_hostile_scene_is_refused_naming_the_cause(service, attack):
    api, *_ = service
    field, fragment = EXPECTED[attack]
    refused(api, ATTACKS[attack](), field, fragment)
    assert api.request("GET", "/healthz")[0] == 200


def test_a_tiny_png_of_nine_megapixels_is_refused_from_its_header(service):
    api, *_ = service
    bomb = png(3000, 3000, "L")
    assert len(bomb) < 16_000
    job = {**small_job("direct"), "targets": {"images": [{"sensor": 0, "data": b64(bomb)}]}}
    refused(api, job, "targets.images[0].data", "9000000 pixels", "NDRF_MAX_IMAGE_PIXELS")


def test_a_film_of_100000_pixels_in_the_xml_is_refused(service):
    api, *_ = service
    xml = SELF_CONTAINED_XML.replace('name="width" value="16"', 'name="width" value="100000"')
    job = scene_job(xml)
    del job["render"]
    refused(api, job, "scene", "100000x12", "NDRF_MAX_RESOLUTION")


NUMBERS = ["learning_rate", "final_learning_rate_ratio", "parameters.0.init", "parameters.0.bounds.1",
           "adam_betas.0", "targets.synthetic.values.red.reflectance.value.0", "training.learning_rate",
           "training.camera_points", "training.residual_clip", "training.radiance.encoding.per_level_scale"]


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_nan_and_infinity_are_refused_in_every_number(service, value):
    api, *_ = service
    for path in NUMBERS:
        job = small_job("direct")
        job["parameters"][0]["bounds"] = [0.0, 1.0]
        job["adam_betas"] = [0.8, 0.99]
        job["training"]["radiance"] = {"encoding": {"per_level_scale": 1.5}}
        node, parts = job, path.split(".")
        while len(parts) > 1:
            head = parts.pop(0)
            if head == "red" and parts[:2] == ["reflectance", "value"]:  # a key with dots
                head, parts = "red.reflectance.value", parts[2:]
            node = node[int(head)] if isinstance(node, list) else node[head]
        last = parts[0]
        if isinstance(node, list):
            node[int(last)] = value
        else:
            node[last] = value
        body = json.dumps(job).encode()                    # Python writes NaN / Infinity literals
        code, _, raw = api.request("POST", "/v1/jobs", raw=body)
        problem = json.loads(raw)
        assert code == 422, (path, problem)
        top = path.split(".")[0]
        assert any(e["field"].startswith(top) for e in problem["errors"]), (path, problem)


def test_the_worker_fails_a_hostile_job_that_bypassed_the_api_and_goes_on(service, tmp_path):
    """Defence in depth: a job written straight into the store (as a compromised API could) is
    checked again by the worker; the job fails naming the file, the worker runs the next job."""
    from schemas.job import JobSpec
    from services.jobs.service import JobService
    from services.queue.redis_queue import RedisJobQueue, connect
    from services.store.local import FolderStore

    api, _, worker, env = service
    service_ = JobService(FolderStore(env["NDRF_STORE"]), RedisJobQueue(connect(env["REDIS_URL"]), 5.0))
    hostile, _ = service_.submit(JobSpec.model_validate(ATTACKS["PLY vertex count past 32 bits"]()))
    job = api.wait_status(hostile.id, {"failed", "succeeded"}, 120)
    assert job["status"] == "failed" and job["field"] == "scene.files[m.ply]" and "4294967297" in job["error"]
    normal = api.json("POST", "/v1/jobs", small_job("direct", iterations=2))[2]["id"]
    assert api.wait_status(normal, {"succeeded", "failed"}, 180)["status"] == "succeeded"
    assert worker.proc.poll() is None


def test_a_job_whose_process_runs_out_of_memory_fails_and_the_worker_goes_on(tmp_path):
    redis = Redis().start()
    env = {"REDIS_URL": redis.url, "NDRF_STORE": str(tmp_path / "store"), "NDRF_LEASE_SECONDS": "5"}
    api_proc, api = start_api(tmp_path, env)
    worker = Process(["-v", "worker", "--name", "tight"], {**env, "NDRF_MAX_CHILD_MEMORY_BYTES": str(300 << 20)},
                     tmp_path / "worker.log")
    try:
        job_id = api.json("POST", "/v1/jobs", small_job("ndrf-rhs", iterations=2))[2]["id"]
        job = api.wait_status(job_id, {"failed", "succeeded"}, 180)
        assert job["status"] == "failed" and "job's process" in job["error"], job
        assert worker.proc.poll() is None and api.request("GET", "/healthz")[0] == 200
    finally:
        for proc in (worker, api_proc):
            proc.kill(signal.SIGKILL)
        redis.kill()


def test_after_every_attack_a_normal_job_finishes_and_the_api_stayed_small(service):
    api, api_proc, worker, _ = service
    job_id = api.json("POST", "/v1/jobs", upload_scene_job())[2]["id"]
    assert api.wait_status(job_id, {"succeeded", "failed"}, 180)["status"] == "succeeded"
    assert worker.proc.poll() is None and api.request("GET", "/healthz")[0] == 200
    peak = _peak_mib(api_proc.proc.pid)
    print(f"API peak resident memory: {peak:.0f} MiB")
    assert peak < API_PEAK_MIB


def upload_scene_job() -> dict:
    job = small_job("direct", iterations=2)
    job.update(scene=upload_scene(), parameters=[{"key": "paint.reflectance.value", "init": 0.5}],
               targets={"synthetic": {"values": {"paint.reflectance.value": [0.3, 0.4, 0.5]}, "spp": 4}})
    return job


def _peak_mib(pid: int) -> float:
    from pathlib import Path

    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    return float("nan")


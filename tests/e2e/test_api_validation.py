"""Untrusted input against a real ``ndrf serve`` process (embedded mode, small caps): malicious
XML, oversized inputs and broken targets get a 4xx problem naming the field; never a 500."""

from __future__ import annotations

import base64
import io
import signal

import numpy as np
import pytest

from harness.cluster import small_job, start_api
from tests.support.scenes import QUAD_OBJ as QUAD
from tests.support.scenes import SELF_CONTAINED_XML
from tests.support.scenes import UPLOAD_MATERIALS as MATERIALS
from tests.support.scenes import UPLOAD_XML as SCENE

CAPS = {"NDRF_MAX_UPLOAD_BYTES": "400000", "NDRF_MAX_RESOLUTION": "128", "NDRF_MAX_SPP": "256",
        "NDRF_MAX_ITERATIONS": "100", "NDRF_MAX_PARAMETERS": "6", "NDRF_MAX_MESH_BYTES": "20000",
        "NDRF_MAX_TEXELS": "1000"}
TEXTURE = {"scene": {"builtin": "textured-box"}, "parameters": [{"key": "wall.reflectance.data", "init": 0.5}],
           "targets": {"synthetic": {"values": {"wall.reflectance.data": None}}}}


def b64(data: bytes | str) -> str:
    return base64.b64encode(data.encode() if isinstance(data, str) else data).decode()


def xml_job(xml=SCENE, files=None, **extra):
    files = {"materials.xml": b64(MATERIALS), "meshes/quad.obj": b64(QUAD)} if files is None else files
    job = small_job("direct", iterations=3)
    job.update(scene={"xml": xml, "files": files}, parameters=[{"key": "paint.reflectance.value", "init": 0.5}],
               targets={"synthetic": {"values": {"paint.reflectance.value": [0.3, 0.4, 0.5]}, "spp": 16}})
    job.update(extra)
    return job


def npy(array) -> str:
    buffer = io.BytesIO()
    np.save(buffer, np.asarray(array, np.float32))
    return b64(buffer.getvalue())


@pytest.fixture(scope="module")
def api(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("validation")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), **CAPS})
    yield api
    proc.kill(signal.SIGKILL)


def expect_problem(api, job, status, field_fragment, message_fragment):
    code, headers, problem = api.json("POST", "/v1/jobs", job)
    assert code == status, problem
    assert headers["content-type"] == "application/problem+json"
    fields = [e["field"] for e in problem.get("errors", [])]
    assert any(field_fragment in f for f in fields), (fields, problem)
    assert message_fragment.lower() in (problem.get("detail") or "").lower(), problem
    return problem


def test_a_valid_uploaded_scene_runs(api):
    code, _, accepted = api.json("POST", "/v1/jobs", xml_job())
    assert code == 202
    assert api.wait_status(accepted["id"], {"succeeded", "failed"}, 120)["status"] == "succeeded"


@pytest.mark.parametrize("xml, files, field, message", [
    (SCENE.replace('filename="materials.xml"', 'filename="/etc/passwd"'), None, "scene.xml", "relative"),
    (SCENE.replace('filename="materials.xml"', 'filename="../../etc/passwd"'), None, "scene.xml", ".."),
    (SCENE.replace('meshes/quad.obj', '/etc/passwd'), None, "scene.xml", "relative to the scene"),
    (SCENE.replace("<include", '<path value="/etc"/><include'), None, "scene.xml", "path"),
    (SCENE, {"materials.xml": b64(MATERIALS), "../meshes/quad.obj": b64(QUAD)}, "scene.files", ".."),
    (SCENE, {"materials.xml": b64(MATERIALS), "/meshes/quad.obj": b64(QUAD)}, "scene.files", "no leading '/'"),
    (SCENE, {"materials.xml": b64(MATERIALS)}, "scene.xml", "not among the uploaded files"),
    ('<?xml version="1.0"?><!DOCTYPE s [<!ENTITY x SYSTEM "file:///etc/passwd">]><scene>&x;</scene>', None,
     "scene.xml", "DTD"),
])
def test_malicious_scenes_are_refused(api, xml, files, field, message):
    expect_problem(api, xml_job(xml, files), 422, field, message)


def test_oversized_body_is_413_before_it_is_read(api):
    """The declared length is over the cap: the answer comes before the body is sent (a client
    that keeps sending 500 KB may see the connection closed instead of reading it)."""
    import json
    import socket
    from urllib.parse import urlparse

    url = urlparse(api.base)
    with socket.create_connection((url.hostname, url.port), timeout=30) as conn:
        conn.sendall(b"POST /v1/jobs HTTP/1.1\r\nHost: x\r\nContent-Type: application/json\r\n"
                     b"Content-Length: 500000\r\n\r\n{")
        response = b""
        while b"\r\n\r\n" not in response or not response.rstrip().endswith(b"}"):
            chunk = conn.recv(65536)
            if not chunk:
                break
            response += chunk
    head, _, body = response.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 413") and b"application/problem+json" in head
    assert "NDRF_MAX_UPLOAD_BYTES" in json.loads(body)["detail"]


@pytest.mark.parametrize("change, field, message", [
    ({"render": {"resolution": [4096, 16]}}, "render.resolution", "NDRF_MAX_RESOLUTION"),
    ({"render": {"spp": 1024}}, "render.spp", "NDRF_MAX_SPP"),
    ({"iterations": 5000}, "iterations", "NDRF_MAX_ITERATIONS"),
    ({"parameters": [{"key": k} for k in ("red.reflectance.value", "green.reflectance.value", "white.reflectance.value")],
      "targets": {"synthetic": {"values": {"red.reflectance.value": 0.5, "green.reflectance.value": 0.5,
                                           "white.reflectance.value": 0.5}}}}, "parameters", "9 scalars"),
    ({"scene": {"path": "/etc/passwd"}}, "scene.path", "host paths"),
    (TEXTURE, "parameters", "4096 texels, more than the limit of 1000 (NDRF_MAX_TEXELS)"),
])
def test_jobs_over_the_caps_are_refused(api, change, field, message):
    expect_problem(api, {**small_job(), **change}, 422, field, message)


def test_a_large_mesh_is_refused(api):
    expect_problem(api, xml_job(files={"materials.xml": b64(MATERIALS), "meshes/quad.obj": b64(QUAD * 1000)}),
                   422, "scene.files[meshes/quad.obj]", "the limit per file")


def test_a_self_contained_scene_without_files_runs(api):
    code, _, accepted = api.json("POST", "/v1/jobs", xml_job(SELF_CONTAINED_XML, files={}))
    assert code == 202, accepted
    assert api.wait_status(accepted["id"], {"succeeded", "failed"}, 120)["status"] == "succeeded"


@pytest.mark.parametrize("data, message", [
    (npy(np.zeros((8, 8, 3))), "film is 16x16"),
    (npy(np.full((16, 16, 3), np.nan)), "NaN"),
    (npy(np.full((16, 16, 3), -1.0)), "negative"),
    (b64(b"definitely not an image"), "unknown image format"),
    ("@@not base64@@", "base64"),
])
def test_bad_target_images_are_refused(api, data, message):
    job = {**small_job(), "targets": {"images": [{"sensor": 0, "data": data}]}}
    expect_problem(api, job, 422, "targets.images[0]", message)


def test_schema_errors_name_the_field(api):
    expect_problem(api, {**small_job(), "method": "magic"}, 422, "method", "ndrf-lhs")
    expect_problem(api, {**small_job(), "unknown_field": 1}, 422, "unknown_field", "not permitted")
    code, headers, _ = api.request("POST", "/v1/jobs", raw=b"{not json")
    assert code == 422 and headers["content-type"] == "application/problem+json"

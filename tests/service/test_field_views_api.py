"""``POST /v1/jobs/{id}/views`` (``api/routes/field_views.py``): bodies out of range are 422s, a
key reaches only its own jobs' views (404 otherwise, as every job route), and a view of a trained
job renders in the sandboxed child and names each file, which can then be read."""

from __future__ import annotations

import numpy as np
import pytest
from fastapi.testclient import TestClient

from harness.cluster import small_job, wait_until
from schemas.errors import InvalidJob
from services.settings import Settings

ALICE, BOB = {"Authorization": "Bearer alice-key"}, {"Authorization": "Bearer bob-key"}
CAMERA = {"origin": [0.3, 0.2, 3.0], "target": [0.0, 0.0, 0.0], "resolution": [16, 16], "spp": 2}


@pytest.fixture(scope="module")
def client(tmp_path_factory):
    from api.app import create_app

    store = tmp_path_factory.mktemp("views-api") / "store"
    with TestClient(create_app(Settings(store=str(store), api_keys=["alice-key", "bob-key"]))) as client:
        yield client


@pytest.mark.parametrize("body", [
    {**CAMERA, "spp": 1000},
    {**CAMERA, "resolution": [4096, 16]},
    {**CAMERA, "prb_spp": 100_000},
    {**CAMERA, "sensor": 0},
    {"origin": [0, 0, 3]},
    {**CAMERA, "fov": 180},
    {**CAMERA, "unknown": 1},
])
def test_view_bodies_out_of_range_are_422(client, body):
    response = client.post("/v1/jobs/0123456789abcdef0123/views", json=body, headers=ALICE)
    assert response.status_code == 422, response.text


def test_views_need_a_key(client):
    assert client.post("/v1/jobs/0123456789abcdef0123/views", json=CAMERA).status_code == 401


@pytest.mark.slow  # a job and a view, each in a sandboxed child: ~30 s
def test_a_view_of_a_trained_job_names_its_files_and_only_its_owner_reaches_it(client):
    submitted = client.post("/v1/jobs", json=small_job("ndrf-lhs", iterations=2), headers=ALICE)
    assert submitted.status_code == 202, submitted.text
    job_id = submitted.json()["id"]

    def finished():
        status = client.get(f"/v1/jobs/{job_id}", headers=ALICE).json()["status"]
        return status if status in ("succeeded", "failed", "canceled") else None

    assert wait_until(finished, 600, 0.3, what="the job") == "succeeded"  # ~10 s on idle cores
    assert client.post(f"/v1/jobs/{job_id}/views", json=CAMERA, headers=BOB).status_code == 404
    response = client.post(f"/v1/jobs/{job_id}/views", json={**CAMERA, "prb_spp": 4}, headers=ALICE)
    assert response.status_code == 201, response.text
    view = response.json()
    assert {"radiance.npy", "radiance.png", "gradients.npy", "gradient-0.png", "prb.npy", "prb-2.png",
            "view.json"} <= set(view["files"])
    assert len(view["scalars"]) == 3 and view["iteration"] == 2
    got = client.get(view["files"]["gradients.npy"], headers=ALICE)
    assert got.status_code == 200
    gradients = np.load(__import__("io").BytesIO(got.content), allow_pickle=False)
    assert gradients.shape == (3, 16, 16, 3) and np.isfinite(gradients).all()
    assert client.get(view["files"]["radiance.png"], headers=BOB).status_code == 404
    assert client.get(f"/v1/jobs/{job_id}/views/{view['id']}/secret.txt", headers=ALICE).status_code == 422
    assert view["warm"] is False                   # the first view started the job's view child
    bad = client.post(f"/v1/jobs/{job_id}/views", json={**CAMERA, "up": [0.3, 0.2, 3.0]}, headers=ALICE)
    assert bad.status_code == 422 and "parallel" in bad.text
    # the warm child answered the bad camera and lives on: the next view reuses it, inline, nothing stored
    moved = {**CAMERA, "origin": [-0.3, 0.2, 3.0], "inline": True}
    inline = client.post(f"/v1/jobs/{job_id}/views", json=moved, headers=ALICE)
    assert inline.status_code == 201, inline.text
    inline = inline.json()
    assert inline["warm"] is True and inline["files"] == {}
    assert set(inline["images"]) == {"radiance.png", "gradient-0.png", "gradient-1.png", "gradient-2.png"}
    png = __import__("base64").b64decode(inline["images"]["gradient-1.png"].split(",", 1)[1])
    assert png.startswith(b"\x89PNG")
    assert inline["images"]["gradient-1.png"] != view_png(client, view["files"]["gradient-1.png"])

    # warm starts from this job: never for another key, never with other parameter keys
    warm = small_job("ndrf-lhs", iterations=1, warm_start={"job": job_id})
    stolen = client.post("/v1/jobs", json=warm, headers=BOB)
    assert stolen.status_code == 422 and "warm_start.job" in stolen.text and "of this API key" in stolen.text
    other = {**warm, "parameters": [{"key": "green.reflectance.value"}],
             "targets": {"synthetic": {"values": {"green.reflectance.value": [0.1, 0.5, 0.1]}, "spp": 16}}}
    refused = client.post("/v1/jobs", json=other, headers=ALICE)
    assert refused.status_code == 422 and "other parameter keys" in refused.text


def view_png(client, url: str) -> str:
    return "data:image/png;base64," + __import__("base64").b64encode(client.get(url, headers=ALICE).content).decode()


def _fake_view(monkeypatch, tmp_path):
    """A job's files with a spec and a checkpoint, and the child's answer faked (no Mitsuba)."""
    from services.jobs import views
    from services.jobs.view_files import write_view
    from services.store.job import JobFiles
    from services.store.local import FolderStore

    files = JobFiles(FolderStore(tmp_path / "store"), "0123456789abcdef0123")
    files.write(JobFiles.SPEC, small_job("ndrf-lhs"))
    files.store.put(files.key(JobFiles.CHECKPOINT), b"weights")
    rng = np.random.default_rng(0)
    arrays = {"radiance": rng.random((8, 8, 3), np.float32), "gradients": rng.normal(size=(3, 8, 8, 3)).astype(np.float32),
              "prb": rng.normal(size=(3, 8, 8, 3)).astype(np.float32)}
    def child(spec, checkpoint, request, limits, out):   # what the child does: the files into out
        written = write_view(out, arrays["radiance"], arrays["gradients"], arrays["prb"] if request.prb_spp else None)
        return {"scalars": ["a", "b", "c"], "seconds": {}, **written}

    monkeypatch.setattr(views, "render_in_child", child)
    return files, arrays


def test_a_view_writes_every_file_it_names(monkeypatch, tmp_path):
    from schemas.views import ViewRequest
    from services.jobs.views import create_view
    from services.settings import Limits

    files, arrays = _fake_view(monkeypatch, tmp_path)
    whole: list[str] = []                               # objects written from bytes in this process's memory
    put = files.store.put
    monkeypatch.setattr(files.store, "put", lambda key, data, **kw: (whole.append(key.rsplit("/", 1)[-1]),
                                                                     put(key, data, **kw)))
    view_id, written, _ = create_view(files, ViewRequest(sensor=0, prb_spp=4), Limits())
    assert whole == ["view.json"]                       # the arrays' files were copied by file
    names = sorted(written)
    assert {"radiance.npy", "radiance.png", "gradients.npy", "prb.npy", "view.json"} <= set(names)
    assert {f"gradient-{p}.png" for p in range(3)} | {f"prb-{p}.png" for p in range(3)} <= set(names)
    for name in names:
        assert files.store.exists(files.key(f"views/{view_id}/{name}")), name
    stored = np.load(files.store.local_path(files.key(f"views/{view_id}/gradients.npy")))
    np.testing.assert_array_equal(stored, arrays["gradients"])
    for name, size in written.items():                 # the sizes of the files copied into the store
        assert files.store.size(files.key(f"views/{view_id}/{name}")) == size, name
    scales = files.store.get_json(files.key(f"views/{view_id}/view.json"))["scales"]
    assert sorted(scales) == ["0", "1", "2"]
    _, inline, _ = create_view(files, ViewRequest(sensor=0, inline=True), Limits())
    assert sorted(inline) == ["gradient-0.png", "gradient-1.png", "gradient-2.png", "radiance.png"]
    assert all(data.startswith(b"\x89PNG") for data in inline.values())


def test_a_view_reads_no_link_the_child_left(monkeypatch, tmp_path):
    from schemas.views import ViewRequest
    from services.jobs import views
    from services.jobs.views import create_view
    from services.settings import Limits

    files, _ = _fake_view(monkeypatch, tmp_path)
    secret = tmp_path / "secret.txt"
    secret.write_text("the API's own file")
    honest = views.render_in_child

    def hostile(spec, checkpoint, request, limits, out):   # radiance.png: a link to a file of the API's
        meta = honest(spec, checkpoint, request, limits, out)
        (out / "radiance.png").unlink()
        (out / "radiance.png").symlink_to(secret)
        return meta

    monkeypatch.setattr(views, "render_in_child", hostile)
    with pytest.raises(InvalidJob, match="view child"):
        create_view(files, ViewRequest(sensor=0), Limits())
    assert not list(files.store.keys(files.prefix + "views/"))


def test_a_view_over_the_jobs_disk_budget_is_refused(monkeypatch, tmp_path):
    from schemas.views import ViewRequest
    from services.jobs.views import OverBudget, create_view
    from services.settings import Limits

    files, _ = _fake_view(monkeypatch, tmp_path)
    with pytest.raises(OverBudget, match="NDRF_MAX_JOB_BYTES"):
        create_view(files, ViewRequest(sensor=0), Limits(job_bytes=1 << 20).model_copy(update={"job_bytes": 2000}))
    assert not list(files.store.keys(files.prefix + "views/"))

"""Experiments against the real service: ``ndrf serve`` and ``ndrf worker`` processes sharing a
real Redis (no persistence) and a store folder, and the embedded default.

* 6 runs with max_concurrent 2 on 2 workers: never more than 2 queued or running (sampled from
  the job records), all 6 finish while a worker is SIGKILLed in the middle of a run, results.csv
  matches the runs' own records, appending 2 seeds adds 2 runs and re-runs nothing;
* retry re-runs only the failed runs; cancel stops the rest and keeps the artifacts;
* a run inside an experiment and the same job submitted alone give the same final parameters;
* the client and ``ndrf submit | watch | fetch | ls --server``.
"""

from __future__ import annotations

import csv
import io
import json
import signal
import threading
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from harness.cluster import small_job, start_api, wait_until


@pytest.fixture()
def store_env(tmp_path):
    """The experiments' own tests read run folders directly: the folder store (the service suite
    runs over both stores)."""
    return {"NDRF_STORE": str(tmp_path / "store")}

FINISHED = {"succeeded", "failed", "canceled"}
ITERATIONS = 30


def job_records(store: Path, exp_id: str) -> list[dict]:
    out = []
    for path in store.glob("*/record.json"):
        try:
            record = json.loads(path.read_text())
        except (OSError, ValueError):
            continue                     # being replaced
        if record.get("experiment") == exp_id:
            out.append(record)
    return out


class Sampler(threading.Thread):
    """Counts the experiment's queued and running jobs from their records, every 50 ms."""

    def __init__(self, store: Path, exp_id: str):
        super().__init__(daemon=True)
        self.store, self.exp_id = store, exp_id
        self.peak_running = self.peak_active = self.samples = 0
        self.stop = threading.Event()

    def run(self):
        while not self.stop.wait(0.05):
            records = job_records(self.store, self.exp_id)
            running = sum(r["status"] == "running" for r in records)
            active = sum(r["status"] in ("queued", "running") for r in records)
            self.peak_running, self.peak_active = max(self.peak_running, running), max(self.peak_active, active)
            self.samples += 1


def wait_experiment(api, exp_id, timeout, statuses=FINISHED):
    def done():
        _, _, experiment = api.json("GET", f"/v1/experiments/{exp_id}")
        return experiment if experiment["status"] in statuses else None
    return wait_until(done, timeout, 0.25, what=f"experiment {exp_id} in {statuses}")


def test_six_runs_two_at_a_time_survive_a_killed_worker_and_append_reruns_nothing(stack):
    api, store = stack.api, Path(stack.env["NDRF_STORE"])
    doomed = stack.add_worker("w1")
    stack.add_worker("w2")
    status, headers, accepted = api.json("POST", "/v1/experiments", {
        "name": "stable over seeds?", "base": small_job("direct", iterations=ITERATIONS, stop={"auto": False}),
        "seeds": [1, 2, 3, 4, 5, 6],
        "max_concurrent": 2})
    assert status == 202 and accepted["runs"] == 6 and headers["location"] == f"/v1/experiments/{accepted['id']}"
    exp_id = accepted["id"]
    sampler = Sampler(store, exp_id)
    sampler.start()

    def victim():           # a run of w1 in the middle of its iterations, once another run has finished
        records = job_records(store, exp_id)
        if not any(r["status"] == "succeeded" for r in records):
            return None
        return next((r for r in records if r["status"] == "running" and r.get("worker") == "w1"
                     and (r.get("iteration") or 0) >= 2), None)

    killed = wait_until(victim, 180, 0.05, what="a run of w1 half-way")
    doomed.kill(signal.SIGKILL)
    experiment = wait_experiment(api, exp_id, 240)
    sampler.stop.set()
    sampler.join()
    assert experiment["status"] == "succeeded", experiment
    assert experiment["counts"] == {"succeeded": 6}
    assert sampler.samples > 50 and sampler.peak_running == 2 and sampler.peak_active <= 2
    taken_over = json.loads((store / killed["id"] / "record.json").read_text())
    assert taken_over["attempts"] == 2 and taken_over["worker"] == "w2"       # resumed by the survivor

    # results.csv is what the runs' own files say
    status, headers, raw = api.request("GET", f"/v1/experiments/{exp_id}/results.csv")
    assert status == 200 and headers["content-type"].startswith("text/csv")
    rows = list(csv.DictReader(io.StringIO(raw.decode())))
    assert sorted(int(r["seed"]) for r in rows) == [1, 2, 3, 4, 5, 6]
    for row in rows:
        job = json.loads((store / row["job"] / "record.json").read_text())
        summary = json.loads((store / row["job"] / "summary.json").read_text())
        records = [json.loads((store / row["job"] / "iterations" / f"{k:06d}" / "record.json").read_text())
                   for k in range(ITERATIONS)]
        assert job["experiment"] == exp_id and job["varied"] == {"seed": int(row["seed"])}
        assert row["status"] == job["status"] == "succeeded" and int(row["iterations"]) == ITERATIONS
        assert float(row["final_loss"]) == records[-1]["loss"]
        assert float(row["final_parameter_error"]) == pytest.approx(summary["estimate_error"], rel=1e-12)
        assert float(row["seconds"]) == pytest.approx(sum(sum(r["seconds"].values()) for r in records), rel=1e-9)
    jobs_before = {r["run"]: r["job"] for r in rows}

    # append 2 seeds: 2 new runs; the 6 finished ones are not run again
    status, _, appended = api.json("POST", f"/v1/experiments/{exp_id}/runs", {"seeds": [7, 8]})
    assert status == 202 and appended["added"] == [6, 7] and appended["runs"] == 8
    experiment = wait_experiment(api, exp_id, 120)
    assert experiment["status"] == "succeeded" and experiment["counts"] == {"succeeded": 8}
    _, _, runs = api.json("GET", f"/v1/experiments/{exp_id}/runs")
    assert {str(r["index"]): r["job"] for r in runs[:6]} == jobs_before
    assert len(job_records(store, exp_id)) == 8 and all(r["attempts"] == 1 for r in runs[6:])
    assert [len(a["configuration"]) for a in experiment["aggregates"]] == [0]      # one configuration...
    assert experiment["aggregates"][0]["succeeded"] == 8                          # ...over 8 seeds


def test_retry_reruns_only_failed_runs_and_cancel_stops_the_rest(stack):
    api, store = stack.api, Path(stack.env["NDRF_STORE"])
    # a disk budget of 1 MiB fails the 192x192 run, not the 16x16 one (its checkpoints keep the floor's
    # residuals and Jacobians per 4x4 block of pixels: 96x96 fit in 1 MiB once the blocks were averaged)
    strict = [stack.add_worker(f"strict{i}", NDRF_MAX_JOB_BYTES=str(1 << 20)) for i in range(2)]
    _, _, accepted = api.json("POST", "/v1/experiments", {
        "base": small_job("direct", iterations=8), "grid": {"render.resolution": [[16, 16], [192, 192]]},
        "max_concurrent": 2})
    exp_id = accepted["id"]
    experiment = wait_experiment(api, exp_id, 180)
    assert experiment["status"] == "failed" and experiment["counts"] == {"succeeded": 1, "failed": 1}
    _, _, runs = api.json("GET", f"/v1/experiments/{exp_id}/runs")
    assert runs[1]["status"] == "failed" and "disk budget" in runs[1]["error"]
    first = [r["job"] for r in runs]
    for worker in strict:
        worker.kill(signal.SIGTERM)
    stack.add_worker("roomy")

    status, _, retried = api.json("POST", f"/v1/experiments/{exp_id}/retry")
    assert status == 202 and retried["added"] == [1]
    experiment = wait_experiment(api, exp_id, 180)
    assert experiment["status"] == "succeeded"
    _, _, runs = api.json("GET", f"/v1/experiments/{exp_id}/runs")
    assert runs[0]["job"] == first[0] and runs[0]["attempts"] == 1            # the succeeded run: untouched
    assert runs[1]["job"] != first[1] and runs[1]["attempts"] == 2 and runs[1]["status"] == "succeeded"
    assert api.json("POST", f"/v1/experiments/{exp_id}/retry")[0] == 409      # nothing left to retry

    # cancel: the 2 running runs stop (keeping their iterations), the 4 pending never start; the
    # runs must still be running when the cancel comes, so no stop rule may end them first
    stack.add_worker("second")
    _, _, accepted = api.json("POST", "/v1/experiments", {
        "base": small_job("direct", iterations=400, stop={"auto": False}), "seeds": [1, 2, 3, 4, 5, 6],
        "max_concurrent": 2})
    long_id = accepted["id"]
    wait_until(lambda: sum(r["status"] == "running" and (r.get("iteration") or 0) >= 1
                           for r in job_records(store, long_id)) == 2, 180, 0.1, what="two runs iterating")
    status, _, canceled = api.json("POST", f"/v1/experiments/{long_id}/cancel")
    assert status == 202 and canceled["counts"].get("canceled") == 4
    experiment = wait_experiment(api, long_id, 60)
    assert experiment["status"] == "canceled" and experiment["counts"] == {"canceled": 6}
    records = job_records(store, long_id)
    assert len(records) == 2 and all(r["status"] == "canceled" for r in records)
    for record in records:
        kept = list((store / record["id"] / "iterations").glob("*/record.json"))
        assert 1 <= len(kept) < 400
    assert api.json("POST", f"/v1/experiments/{long_id}/cancel")[0] == 409


@pytest.fixture(scope="module")
def embedded(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("experiments-embedded")
    proc, api = start_api(tmp, {"NDRF_STORE": str(tmp / "store"), "NDRF_API_KEYS": "k1,k2",
                                "NDRF_EMBEDDED_WORKERS": "2"})
    yield api, tmp / "store"
    proc.kill(signal.SIGKILL)


def test_a_run_of_an_experiment_equals_the_same_job_alone(embedded):
    api, store = embedded
    base = small_job("prb", iterations=4, seed=5)
    _, _, accepted = api.json("POST", "/v1/experiments", {"base": base, "grid": {"learning_rate": [0.08]}})
    _, _, alone = api.json("POST", "/v1/jobs", dict(base, learning_rate=0.08))
    experiment = wait_experiment(api, accepted["id"], 180)
    job = api.wait_status(alone["id"], FINISHED, 180)
    assert experiment["status"] == job["status"] == "succeeded"
    run_job = api.json("GET", f"/v1/experiments/{accepted['id']}/runs")[2][0]["job"]
    inside = json.loads((store / run_job / "summary.json").read_text())["estimate"]
    outside = json.loads((store / alone["id"] / "summary.json").read_text())["estimate"]
    # different processes: equal up to float rounding of kernels traced anew and of Dr.Jit's atomic
    # adds into the gradient (tests/service/test_loop.py); CI measured 1.25e-6 relative after 4
    # iterations, where another seed moves the answer by ~1e-2
    np.testing.assert_allclose(inside, outside, rtol=1e-5, atol=1e-9)
    assert inside != base["parameters"][0]["init"]


def test_experiments_are_checked_before_anything_is_queued_and_belong_to_their_key(embedded):
    api, store = embedded
    jobs_before = len(list(store.glob("*/record.json")))
    status, _, problem = api.json("POST", "/v1/experiments", {          # 2 values for an RGB: only the scene knows
        "base": small_job("direct"), "grid": {"parameters[red.reflectance.value].init": [0.2, [0.1, 0.2]]},
        "seeds": [1, 2]})
    assert status == 422 and problem["type"] == "/problems/invalid-experiment"
    assert problem["errors"][0]["field"] == "runs[2].parameters[0].init"         # the scene check names the run
    assert "has 2 values" in problem["errors"][0]["message"]
    status, _, problem = api.json("POST", "/v1/experiments", {"base": small_job(), "grid": {"render.nope": [1]}})
    assert status == 422 and problem["errors"][0]["field"] == "grid.render.nope"
    status, _, problem = api.json("POST", "/v1/experiments", {"base": small_job(), "seeds": list(range(300))})
    assert status == 422 and "NDRF_MAX_EXPERIMENT_RUNS" in problem["detail"]
    assert len(list(store.glob("*/record.json"))) == jobs_before           # no job was created

    from harness.cluster import Api

    other = Api(api.base, "k2")
    _, _, mine = api.json("POST", "/v1/experiments", {"base": small_job("direct", iterations=2)})
    assert other.json("GET", f"/v1/experiments/{mine['id']}")[0] == 404
    assert other.json("POST", f"/v1/experiments/{mine['id']}/cancel")[0] == 404
    assert [e["id"] for e in other.json("GET", "/v1/experiments")[2]["items"]] == []
    experiment = wait_experiment(api, mine["id"], 120)
    assert experiment["read_token"] and experiment["status"] == "succeeded"
    status, _, raw = Api(api.base).request("GET", f"/v1/experiments/{mine['id']}/results.csv"
                                                  f"?token={experiment['read_token']}")
    assert status == 200 and raw.startswith(b"run,job,status,seed")


def test_cli_and_client_talk_to_a_server(embedded, tmp_path, monkeypatch):
    from cli.main import main
    from client import Client

    api, _ = embedded
    monkeypatch.setenv("NDRF_API_KEY", "k1")
    job_file = tmp_path / "job.json"
    job_file.write_text(json.dumps(small_job("direct", iterations=3)))
    runner = CliRunner()
    result = runner.invoke(main, ["submit", str(job_file), "--server", api.base])
    assert result.exit_code == 0, result.output
    kind, job_id, _ = result.output.split()[:3]
    assert kind == "job"
    result = runner.invoke(main, ["watch", job_id, "--server", api.base])
    assert result.exit_code == 0 and f"{job_id}: succeeded" in result.output, result.output
    result = runner.invoke(main, ["fetch", job_id, "--server", api.base, "--out", str(tmp_path / "fetched")])
    assert result.exit_code == 0, result.output
    fetched = tmp_path / "fetched"
    assert len(json.loads((fetched / "iterations.json").read_text())) == 3
    assert (fetched / "iterations" / "000002" / "render.png").read_bytes()[:4] == b"\x89PNG"
    assert (fetched / "checkpoints" / "latest.pt").stat().st_size > 0
    assert (fetched / "targets" / "target-0.png").exists() and (fetched / "targets" / "target-0.exr").exists()

    spec_file = tmp_path / "experiment.json"
    spec_file.write_text(json.dumps({"base": small_job("direct", iterations=2), "seeds": [1, 2]}))
    result = runner.invoke(main, ["submit", str(spec_file), "--server", api.base, "--watch"])
    assert result.exit_code == 0 and "experiment e" in result.output, result.output
    exp_id = result.output.split()[1]
    result = runner.invoke(main, ["ls", "--server", api.base])
    assert result.exit_code == 0 and job_id in result.output and exp_id in result.output
    result = runner.invoke(main, ["fetch", exp_id, "--server", api.base, "--out", str(tmp_path / "exp"), "--runs"])
    assert result.exit_code == 0, result.output
    assert len((tmp_path / "exp" / "results.csv").read_text().splitlines()) == 3

    client = Client(api.base, "k1")
    events = list(client.events(exp_id))                         # replayed from the start, ends at the end
    assert events[-1]["type"] == "status" and events[-1]["status"] == "succeeded"
    seqs = [e["seq"] for e in events]
    assert seqs == sorted(seqs) and list(client.events(exp_id, after=seqs[2]))[0]["seq"] == seqs[3]
    assert _refused(Client(api.base, "wrong"))


def _refused(client) -> bool:
    from client import ApiError

    try:
        client.jobs()
    except ApiError as exc:
        return exc.status == 401
    return False


def test_a_pose_and_an_albedo_run_in_one_experiment_through_the_service(embedded, tmp_path, monkeypatch):
    """Geometry runs through the service, not only ``ndrf run``: ``examples/experiment-pose-albedo.json``
    (the block's pose, then the floor's albedo) as one experiment; the pose run serves its
    silhouettes and its recovered pose (the 4x4 matrix and the XML), the albedo run neither."""
    api, _ = embedded
    example = json.loads((Path(__file__).resolve().parents[2] / "examples" / "experiment-pose-albedo.json").read_text())
    example["base"].update(iterations=4, images_every=1)
    _, _, accepted = api.json("POST", "/v1/experiments", example)
    experiment = wait_experiment(api, accepted["id"], 300)
    assert experiment["status"] == "succeeded", experiment
    runs = [run["job"] for run in api.json("GET", f"/v1/experiments/{accepted['id']}/runs")[2]]
    pose, albedo = (api.json("GET", f"/v1/jobs/{job}")[2] for job in runs)
    assert pose["plan"]["recipe"]["method"].endswith("-projective") and "block.to_world.rotate[1]" in pose["estimate"]
    status, _, png = api.request("GET", f"/v1/jobs/{pose['id']}/iterations/0/silhouette.png")
    assert status == 200 and png.startswith(b"\x89PNG")
    status, _, poses = api.json("GET", f"/v1/jobs/{pose['id']}/final/poses.json")
    assert status == 200 and [entry["shape"] for entry in poses] == ["block"]
    assert np.asarray(poses[0]["matrix"]).shape == (4, 4) and "<transform" in poses[0]["xml"]
    assert api.request("GET", f"/v1/jobs/{albedo['id']}/final/poses.json")[0] == 404
    assert api.request("GET", f"/v1/jobs/{albedo['id']}/iterations/0/silhouette.png")[0] == 404
    from cli.main import main
    monkeypatch.setenv("NDRF_API_KEY", "k1")
    fetched = tmp_path / "fetched"
    result = CliRunner().invoke(main, ["fetch", pose["id"], "--server", api.base, "--out", str(fetched)])
    assert result.exit_code == 0, result.output
    assert json.loads((fetched / "final" / "poses.json").read_text()) == poses


def test_a_shape_jobs_mesh_is_served_and_fetched(embedded, tmp_path, monkeypatch):
    """``examples/shape.json``, shortened, through the embedded service: the recovered mesh is
    served as PLY and ``ndrf fetch`` writes it where ``ndrf run`` would, ``final/<shape id>.ply``."""
    from cli.main import main
    api, _ = embedded
    job = json.loads((Path(__file__).resolve().parents[2] / "examples" / "shape.json").read_text())
    job.update(iterations=3, render={"resolution": [16, 16]})
    job["targets"]["synthetic"]["spp"] = 16
    _, _, accepted = api.json("POST", "/v1/jobs", job)
    assert api.wait_status(accepted["id"], FINISHED, 180)["status"] == "succeeded"
    status, _, ply = api.request("GET", f"/v1/jobs/{accepted['id']}/final/sphere.ply")
    assert status == 200 and ply.startswith(b"ply")
    monkeypatch.setenv("NDRF_API_KEY", "k1")
    fetched = tmp_path / "fetched"
    result = CliRunner().invoke(main, ["fetch", accepted["id"], "--server", api.base, "--out", str(fetched)])
    assert result.exit_code == 0, result.output
    assert (fetched / "final" / "sphere.ply").read_bytes() == ply
    assert not (fetched / "final" / "poses.json").exists()

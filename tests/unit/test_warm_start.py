"""Warm starts (``services/jobs/warm_start.py``, ``services/solver/optimize/warm_start.py``): a
source with another scene, other keys or other field settings is refused naming the mismatch; a
source of another tenant is refused as unknown; a warm-started run reuses the fields, tops up
instead of warming up, and says so in plan.json."""

from __future__ import annotations

import json

import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.records import JobRecord, JobStatus
from services.jobs.state import JobStates, now_iso
from services.jobs.warm_start import mismatch, source_checkpoint
from services.store.job import JobFiles
from services.store.local import FolderStore
from tests.support.jobs import run_job, small_job

SOURCE = "0123456789abcdef0123"


def _spec(**extra) -> JobSpec:
    return JobSpec.model_validate({**small_job("ndrf-lhs"), "warm_start": {"job": SOURCE}, **extra})


@pytest.mark.parametrize("change, named", [
    ({"scene": {"builtin": "hidden-object"}}, "another scene ('hidden-object' here, 'cornell-box' there)"),
    ({"parameters": [{"key": "green.reflectance.value"}],
      "targets": {"synthetic": {"values": {"green.reflectance.value": [0.1, 0.5, 0.1]}}}}, "other parameter keys"),
    ({"training": {**small_job()["training"], "differential": {"mlp": {"hidden_width": 32}}}}, "training.differential"),
    ({"effects": {"merge_channels": False}}, "effects"),
])
def test_a_mismatched_source_is_refused_naming_the_mismatch(change, named):
    source = JobSpec.model_validate(small_job("ndrf-lhs"))
    assert mismatch(_spec(), source, SOURCE) is None
    assert named in (mismatch(_spec(**change), source, SOURCE) or "")


def test_without_warm_start_the_fingerprint_is_unchanged():
    """Checkpoints and idempotency keys of jobs written before the field (and the later ``stop``,
    ``textures.resolution``, ``geometry``, ``targets.synthetic.meshes`` and ``hessian: auto``) keep matching: the hash
    of the fields the job had then, and the value the version before those fields computed for
    this job."""
    import hashlib

    spec = JobSpec.model_validate(small_job("ndrf-lhs"))
    before = {"name": True, "warm_start": True, "stop": True, "textures": {"resolution"}, "geometry": True,
              "targets": {"synthetic": {"meshes"}}}
    then = spec.model_copy(update={"hessian": "successive"})   # the default before hessian: auto
    old = hashlib.sha256(then.model_dump_json(exclude=before).encode()).hexdigest()[:16]
    assert spec.fingerprint() == old == "f5065dd0afb6bd96" != _spec().fingerprint()
    assert JobSpec.model_validate(small_job("ndrf-lhs", stop={"standard_error": 0.01})).fingerprint() != old


def _store_source(tmp_path, owner: str, checkpoint: bytes | None = b"weights") -> JobStates:
    states = JobStates(FolderStore(tmp_path / "store"))
    files = states.files(SOURCE)
    files.write(JobFiles.SPEC, small_job("ndrf-lhs"))
    now = now_iso()
    states.create(JobRecord(id=SOURCE, owner=owner, status=JobStatus.SUCCEEDED, method="ndrf-lhs",
                            scene="cornell-box", created=now, updated=now, iterations=6))
    if checkpoint is not None:
        files.store.put(files.key(JobFiles.CHECKPOINT), checkpoint)
    return states


def test_the_source_resolves_within_the_tenant_only(tmp_path):
    states = _store_source(tmp_path, owner="alice")
    assert source_checkpoint(states, _spec(), "alice") == b"weights"
    assert source_checkpoint(states, _spec(), "alice", read=False) is None      # checked only
    with pytest.raises(InvalidJob, match=f"no job '{SOURCE}' of this API key") as refused:
        source_checkpoint(states, _spec(), "bob")
    assert refused.value.field == "warm_start.job"
    with pytest.raises(InvalidJob, match="no job"):
        source_checkpoint(states, _spec(warm_start={"job": "fedcba98765432100123"}), "alice")
    assert source_checkpoint(states, JobSpec.model_validate(small_job("ndrf-lhs")), "alice") is None


def test_a_source_without_a_checkpoint_is_refused(tmp_path):
    states = _store_source(tmp_path, owner="alice", checkpoint=None)
    with pytest.raises(InvalidJob, match="no checkpoint yet"):
        source_checkpoint(states, _spec(), "alice", read=False)


@pytest.mark.slow  # two small jobs: ~20 s on 2 busy cores
def test_a_warm_started_run_reuses_the_fields_and_tops_up_instead_of_warming_up(tmp_path, mi):
    assert run_job(small_job("ndrf-lhs", iterations=2), tmp_path / "first")["status"] == "succeeded"
    job = small_job("ndrf-lhs", iterations=2, seed=5, warm_start={"job": "first", "top_up_steps": 3})
    assert run_job(job, tmp_path / "second")["status"] == "succeeded"
    plan = json.loads((tmp_path / "second" / "plan.json").read_text())
    reused = plan["warm_start"]
    assert reused["job"] == "first" and reused["fields"] == ["radiance", "differential"]
    assert reused["parameters"] is False and reused["source_iteration"] == 2
    assert 1 <= reused["top_up_steps"] <= 3 and reused["warmup_steps_saved"] >= 10 - 3
    first = json.loads((tmp_path / "second" / "iterations" / "000000" / "record.json").read_text())
    assert first["training_steps"] == 0  # no warm-up at iteration 0: the top-up replaced it
    cold = json.loads((tmp_path / "first" / "iterations" / "000000" / "record.json").read_text())
    assert cold["training_steps"] == 10

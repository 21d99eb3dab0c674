"""The sandboxed child processes: whatever a scene does to the loader, the parent gets a clear
description and goes on. Mitsuba is only ever loaded in the children here."""

from __future__ import annotations

import io
import os
import struct
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from services.jobs.frames import FrameError, array_bytes, array_from, read_frame, write_frame
from services.jobs.isolation import ROOT, ChildFailed, ChildLimits, exchange

PLY_OVERFLOW_HEADER = (b"ply\nformat binary_little_endian 1.0\nelement vertex 4294967297\nproperty float x\n"
                       b"property float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\n"
                       b"end_header\n")


def test_frames_round_trip_and_refuse_what_a_hostile_child_could_send():
    stream = io.BytesIO()
    write_frame(stream, "iteration", {"k": 1}, {"a": array_bytes(np.arange(6, dtype=np.float32).reshape(2, 3))})
    write_frame(stream, "outcome", {"status": "succeeded"})
    stream.seek(0)
    kind, meta, blobs = read_frame(stream)
    assert (kind, meta) == ("iteration", {"k": 1}) and array_from(blobs["a"], ndim=2).shape == (2, 3)
    assert read_frame(stream)[0] == "outcome" and read_frame(stream) is None
    with pytest.raises(FrameError, match="exceeds"):
        read_frame(io.BytesIO(struct.pack(">Q", 1 << 40)))
    with pytest.raises(FrameError, match="ended"):
        read_frame(io.BytesIO(struct.pack(">Q", 100) + b"{}"))
    pickled = io.BytesIO()
    np.save(pickled, np.array([object()], dtype=object), allow_pickle=True)
    with pytest.raises(FrameError):
        array_from(pickled.getvalue())                        # never unpickles what a child sends


def _check_start(tmp_path, ply_body: bytes):
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "m.ply").write_bytes(PLY_OVERFLOW_HEADER + ply_body)
    xml = '<scene version="3.0.0"><shape type="ply"><string name="filename" value="m.ply"/></shape></scene>'
    (tmp_path / "scene" / "scene.xml").write_text(xml)
    spec = {"scene": {"xml": xml}, "parameters": [{"key": "x"}],
            "targets": {"synthetic": {"values": {"x": 0.5}}}}
    return {"spec": spec, "scene_file": str(tmp_path / "scene" / "scene.xml")}


def test_a_loader_crash_is_described_with_the_file_it_was_reading(tmp_path):
    """The PLY header overflow of issue 13, given to Mitsuba directly (no Python check before it):
    the child dies by a signal and the parent names it and the file."""
    # Whether the overflowed reads crash depends on the heap's layout: most runs do, some read to
    # the end of the file first and report it cleanly ("read 11136 out of 12288 bytes"), about one
    # in three in the sandbox (whose set-up moves the heap), none in 15 runs without it. So: the
    # clean report is accepted, and the crash must come within a few attempts.
    start = _check_start(tmp_path, struct.pack("<3f", 0, 0, 0) * 4000)
    for _ in range(10):
        try:
            kind, meta = exchange("check", start, ChildLimits(wall_seconds=60), tmp_path, "the scene loader")
        except ChildFailed as exc:
            failed = exc
            break
        assert kind == "invalid" and "m.ply" in meta["message"] and "out of" in meta["message"], meta
    else:
        pytest.fail("the overflowing PLY never crashed the loader in 10 attempts")
    message = str(failed)
    assert message.startswith("the scene loader crashed (SIG") and message.endswith("reading m.ply"), message


def test_a_child_over_its_wall_clock_is_stopped(tmp_path):
    start = _check_start(tmp_path, b"")
    with pytest.raises(ChildFailed, match=r"took longer than 0.2 s"):
        exchange("check", start, ChildLimits(wall_seconds=0.2), tmp_path, "the scene loader")


#: The address-space limit of the memory test. Measured on the 2-core CI machine (VmPeak of the check
#: child, no limit): 1101 MiB with a 16 x 16 poster (328 MiB resident), 1804 MiB with an 8192 x 8192
#: one (1029 MiB resident). 1.5 GiB lies between, with room on both sides.
MEMORY_LIMIT = 1536 << 20


def _poster_start(folder: Path, side: int) -> dict:
    """A harmless scene to check: a quad in sky light beside a ``side x side`` black PNG poster (an
    8192 x 8192 one is 195 KB on disk)."""
    from tests.support.payloads import png
    from tests.support.scenes import SELF_CONTAINED_XML

    (folder / "scene").mkdir()
    (folder / "scene" / "poster.png").write_bytes(png(side, side))
    poster = ('<bsdf type="diffuse" id="poster"><texture type="bitmap" name="reflectance">'
              '<string name="filename" value="poster.png"/></texture></bsdf>'
              '<shape type="rectangle"><transform name="to_world"><translate z="-1"/></transform>'
              '<ref id="poster"/></shape></scene>')
    xml = SELF_CONTAINED_XML.replace("</scene>", poster)
    (folder / "scene" / "scene.xml").write_text(xml)
    spec = {"scene": {"xml": xml}, "parameters": [{"key": "paint.reflectance.value"}],
            "targets": {"synthetic": {"values": {"paint.reflectance.value": 0.5}}}}
    return {"spec": spec, "scene_file": str(folder / "scene" / "scene.xml")}


def test_a_child_over_its_memory_limit_fails_cleanly(tmp_path):
    """A scene with nothing hostile in it whose 8K poster needs about 1 GB once loaded: under a
    1.5 GiB address-space limit the check child fails and the parent describes it (Mitsuba does not
    survive a failed allocation: a crash, or a MemoryError where Python allocates). The control: a
    poster of 16 x 16 under the same limit is checked, so the limit, not the child's start, is what
    the large one meets. Without the limit the large poster is checked too (issue 36 shows it)."""
    small, large = tmp_path / "small", tmp_path / "large"
    small.mkdir(), large.mkdir()
    limits = ChildLimits(memory_bytes=MEMORY_LIMIT, wall_seconds=600)
    kind, _ = exchange("check", _poster_start(small, 16), limits, small, "the scene loader")
    assert kind == "checked"
    with pytest.raises(ChildFailed, match=r"ran out of memory|crashed \(SIG"):
        exchange("check", _poster_start(large, 8192), limits, large, "the scene loader")


def test_the_child_environment_holds_no_secrets(tmp_path, monkeypatch):
    from services.jobs.isolation import _environment

    monkeypatch.setenv("NDRF_API_KEYS", "s3cret")
    monkeypatch.setenv("REDIS_URL", "redis://x")
    monkeypatch.setenv("AWS_SECRET_ACCESS_KEY", "k")
    env = _environment()
    assert not {"NDRF_API_KEYS", "REDIS_URL", "AWS_SECRET_ACCESS_KEY"} & set(env)


def test_a_job_canceled_as_its_process_starts_is_canceled_not_crashed(tmp_path):
    """The stop signal may reach the child before it installed its handler (during interpreter
    start-up): it dies of that signal, which is the stop that was asked for, not a crash."""
    import threading

    from harness.cluster import small_job
    from schemas.job import JobSpec
    from schemas.outcomes import Outcome
    from schemas.records import JobRecord, JobStatus
    from services.jobs.runner import AttemptRunner
    from services.jobs.state import JobStates, now_iso
    from services.settings import Limits
    from services.store.local import FolderStore

    states = JobStates(FolderStore(tmp_path / "store"))
    job_id, now = "0" * 19 + "1", now_iso()
    spec = JobSpec.model_validate(small_job())
    states.files(job_id).write("spec.json", spec.model_dump(mode="json"))
    states.create(JobRecord(id=job_id, status=JobStatus.QUEUED, method=spec.method.value, scene="cornell-box",
                            created=now, updated=now, iterations=spec.iterations))
    states.transition(job_id, JobStatus.RUNNING, attempt="w#1")
    runner = AttemptRunner(states, Limits(), tmp_path / "scratch")
    result = runner.run(job_id, "w#1", lost=threading.Event(), stop=lambda: Outcome.CANCELED)
    assert result.outcome is Outcome.CANCELED and states.get(job_id).status is JobStatus.CANCELED


@pytest.mark.skipif(not Path("/proc/self/autogroup").exists(), reason="no autogroup scheduling on this kernel")
def test_a_child_in_a_new_session_keeps_the_niceness_of_a_niced_worker():
    """With autogroup scheduling, a new session starts at nice 0 whatever its process's nice: a
    worker run at ``nice 19`` would start jobs as loud as the API beside it. ``apply_limits`` (first
    thing in every child) hands the child's nice to its session."""
    def session_nice(worker_nice: int) -> str:
        probe = (f"import os; os.nice({worker_nice}); from services.jobs.isolation import apply_limits, ChildLimits;"
                 "from dataclasses import asdict; apply_limits(asdict(ChildLimits()));"
                 "print(open('/proc/self/autogroup').read().split()[-1])")
        done = subprocess.run([sys.executable, "-c", probe], cwd=ROOT, capture_output=True, text=True, timeout=60,
                              start_new_session=True, env={**os.environ, "PYTHONPATH": str(ROOT)})
        assert done.returncode == 0, done.stderr
        return done.stdout.strip()

    assert session_nice(7) == "7"
    assert session_nice(0) == "0"                             # a worker at nice 0: nothing changed


def _probe(tmp_path, start: dict, hide: tuple[str, ...] = ()) -> dict:
    work = tmp_path / "scratch" / "job-1"
    work.mkdir(parents=True, exist_ok=True)
    kind, report = exchange("probe", start, ChildLimits(wall_seconds=60, hide=hide), work, "the probe")
    assert kind == "probed"
    return report


@pytest.fixture()
def sandbox_on(monkeypatch):
    from services.jobs import sandbox
    from services.settings import get_settings

    command, why = sandbox.probe()
    if command is None:
        pytest.skip(f"this machine cannot create the child's namespaces: {why}")
    monkeypatch.setenv("NDRF_SANDBOX", "required")
    get_settings.cache_clear()
    yield
    get_settings.cache_clear()


def test_a_sandboxed_child_cannot_write_the_store_nor_reach_redis(tmp_path, redis_server, sandbox_on, monkeypatch):
    """Issue 27, point 9, from inside a child: creating a file in the store folder fails (the
    filesystem is read-only but the child's work folder), and so does connecting to Redis on
    127.0.0.1 (a network namespace of its own); the store it was told to hide is empty to it, other
    jobs' scratch folders are out of sight, and it has no capability left to undo any of this."""
    import socket

    from services.settings import get_settings

    store = tmp_path / "store"
    (store / "0000000000000000001").mkdir(parents=True)
    (store / "0000000000000000001" / "record.json").write_text("{}")
    (tmp_path / "scratch" / "job-2").mkdir(parents=True)          # another job's scratch folder
    host, port = "127.0.0.1", int(redis_server.url.rsplit(":", 1)[1].split("/")[0])
    socket.create_connection((host, port), timeout=2).close()     # reachable from here
    start = {"write": [str(store), str(store / "0000000000000000001"), str(tmp_path)],
             "connect": [[host, port]], "list": [str(store), str(tmp_path / "scratch")],
             "unmount": [str(store), "/"]}
    seen = _probe(tmp_path, start)                                # the store read-only, not hidden
    assert all(v.startswith("refused: Read-only file system") for v in seen["write"].values()), seen
    assert seen["connect"][f"{host}:{port}"].startswith("refused"), seen
    assert seen["list"][str(tmp_path / "scratch")] == "ok: ['job-1']", seen
    assert all(v.startswith("refused") for v in seen["unmount"].values()), seen
    assert seen["capabilities"] == "0" and seen["cwd_writable"].startswith("ok"), seen
    # /proc stays writable (CUDA does not start otherwise, issue 35); the kernel's settings do not
    assert seen["mounts"]["/"].startswith("ro") and seen["mounts"]["/proc"].startswith("rw"), seen["mounts"]
    assert seen["mounts"]["/proc/sys"].startswith("ro"), seen["mounts"]
    secret = tmp_path / "credentials"
    secret.write_text("aws_secret_access_key = k")
    unix = socket.socket(socket.AF_UNIX)                          # Redis on a Unix socket: a read-only
    unix.bind(str(tmp_path / "redis.sock"))                       # mount does not stop connect()
    unix.listen(1)
    monkeypatch.setenv("NDRF_SANDBOX_HIDE", f"{secret},{tmp_path / 'redis.sock'}")
    get_settings.cache_clear()
    nested = str(tmp_path / "scratch" / "job-2")                  # inside the hidden scratch root: no error
    hidden = _probe(tmp_path, {**start, "read": [str(secret)], "connect": [[str(tmp_path / "redis.sock"), 0]]},
                    hide=(str(store), nested))                    # ... hidden too
    unix.close()
    assert hidden["connect"][f"{tmp_path / 'redis.sock'}:0"].startswith("refused"), hidden
    assert hidden["list"][str(store)] == "ok: []", hidden
    assert hidden["write"][str(store)].startswith("refused"), hidden
    assert hidden["read"][str(secret)] == "ok: ", hidden       # NDRF_SANDBOX_HIDE: reads empty
    assert sorted(p.name for p in store.iterdir()) == ["0000000000000000001"]   # nothing was written
    assert [p.name for p in (store / "0000000000000000001").iterdir()] == ["record.json"]


def test_without_the_sandbox_the_same_probe_writes_and_connects(tmp_path, redis_server, monkeypatch):
    """The control of the test above (and what ``NDRF_SANDBOX=off``, or a machine without
    namespaces, leaves): the same child writes the store and reaches Redis."""
    from services.settings import get_settings

    monkeypatch.setenv("NDRF_SANDBOX", "off")
    get_settings.cache_clear()
    try:
        store = tmp_path / "store"
        store.mkdir()
        port = int(redis_server.url.rsplit(":", 1)[1].split("/")[0])
        seen = _probe(tmp_path, {"write": [str(store)], "connect": [["127.0.0.1", port]]})
    finally:
        get_settings.cache_clear()
    assert seen["write"][str(store)].startswith("ok") and seen["connect"][f"127.0.0.1:{port}"].startswith("ok"), seen


def test_required_sandbox_refuses_to_start_a_child_where_namespaces_fail(tmp_path, monkeypatch):
    """``NDRF_SANDBOX=required`` on a machine without namespaces: no child starts (the job or the
    upload fails with the reason), rather than one that could write the store."""
    from services.jobs import sandbox
    from services.settings import get_settings

    monkeypatch.setenv("NDRF_SANDBOX", "required")
    monkeypatch.setattr(sandbox, "probe", lambda: (None, "unshare: operation not permitted"))
    sandbox.command_prefix.cache_clear()
    get_settings.cache_clear()
    try:
        with pytest.raises(ChildFailed, match="NDRF_SANDBOX=required"):
            _probe(tmp_path, {})
    finally:
        sandbox.command_prefix.cache_clear()
        get_settings.cache_clear()


def test_a_sandboxed_run_keeps_kernels_in_its_keys_own_cache(tmp_path, sandbox_on):
    """Dr.Jit's kernel cache of a run is the folder of its job's key (kept across its jobs, writable),
    not the shared cache: what one key's child compiles (or plants) no other key's child loads."""
    kernels = tmp_path / "scratch" / "kernels"
    (kernels / "key-a").mkdir(parents=True)
    (kernels / "key-b").mkdir()
    (kernels / "key-b" / "kernel.bin").write_text("b's")
    work = tmp_path / "scratch" / "job-1"
    work.mkdir()
    kind, seen = exchange("probe", {"write": ["/dev/shm/drjit-cache"], "list": [str(kernels)]},
                          ChildLimits(wall_seconds=60, kernel_cache=str(kernels / "key-a")), work, "the probe")
    assert seen["write"]["/dev/shm/drjit-cache"].startswith("ok"), seen
    assert seen["list"][str(kernels)].startswith("refused"), seen          # under the hidden scratch root
    assert len(list((kernels / "key-a").iterdir())) == 1                    # kept by the parent
    assert [p.name for p in (kernels / "key-b").iterdir()] == ["kernel.bin"]

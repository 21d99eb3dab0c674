"""The artifact stores: the folder store and the S3 store (against moto's S3 server on loopback,
tests/support/s3server.py) pass the same tests where their semantics agree: atomic writes,
compare-and-set, event logs, listing, deleting, streaming. Then what only one of them has."""

from __future__ import annotations

import errno
import io
import os
import threading
import urllib.request

import numpy as np
import pytest

from services.store.base import StoreFull
from services.store.local import FolderStore


@pytest.fixture(params=["folder", "s3"])
def store(request, tmp_path):
    if request.param == "folder":
        return FolderStore(tmp_path)
    return request.getfixturevalue("s3_store")


# ----------------------------------------------------------------------------------- both stores

def test_get_put_exists_size_and_json(store):
    assert store.get("job/record.json") is None and not store.exists("job/record.json")
    assert store.size("job/record.json") is None and store.get_versioned("job/record.json") is None
    store.put_json("job/record.json", {"a": 1})
    store.put_json("job/record.json", {"a": 2})                     # a whole-object overwrite
    assert store.get_json("job/record.json") == {"a": 2} and store.exists("job/record.json")
    assert store.size("job/record.json") == len(store.get("job/record.json"))
    assert store.get_json("job/missing.json", default={"d": 0}) == {"d": 0}


def test_put_file_copies_the_first_size_bytes_of_a_file_by_chunks(store, tmp_path, monkeypatch):
    from services.store import files

    monkeypatch.setattr(files, "CHUNK_BYTES", 1000)                 # several chunks for the folder store
    data = os.urandom(6 << 20) + b"written after its size was read"   # over S3's 5 MiB: a multipart upload
    path = tmp_path / "child-wrote.npy"
    path.write_bytes(data)
    with path.open("rb") as handle:
        store.put_file("job/views/0123456789ab/radiance.npy", handle, 6 << 20)
    assert store.get("job/views/0123456789ab/radiance.npy") == data[:6 << 20]
    with path.open("rb") as handle, pytest.raises(OSError):         # shorter than said: nothing written
        store.put_file("job/views/0123456789ab/short.npy", handle, len(data) + 1)
    assert not store.exists("job/views/0123456789ab/short.npy")


def test_json_is_written_with_non_finite_numbers_as_null(store):
    store.put_json("x.json", {"a": float("nan"), "b": [1.0, float("inf")], "c": np.float32(2)})
    assert store.get_json("x.json") == {"a": None, "b": [1.0, None], "c": 2.0}


def test_put_if_is_a_compare_and_set(store):
    assert store.put_if("k", b"one", None) is not None          # create
    assert store.put_if("k", b"again", None) is None            # exists: refused
    data, version = store.get_versioned("k")
    assert data == b"one"
    assert store.put_if("k", b"two", "not-the-version") is None
    newer = store.put_if("k", b"two", version)
    assert newer is not None and store.get("k") == b"two"
    assert store.put_if("k", b"three", version) is None         # the old version lost
    assert store.get_versioned("k") == (b"two", newer)
    assert store.put_if("never-created", b"x", version) is None  # an update of nothing is refused


def test_concurrent_compare_and_set_has_one_winner_per_version(store):
    store.put("counter", b"0")
    wins = []

    def bump():
        for _ in range(25):
            while True:
                data, version = store.get_versioned("counter")
                if store.put_if("counter", str(int(data) + 1).encode(), version) is not None:
                    wins.append(1)
                    break

    threads = [threading.Thread(target=bump) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert store.get("counter") == b"100" and len(wins) == 100     # no lost update


def test_concurrent_creates_have_exactly_one_winner(store):
    for round_ in range(10):
        winners, barrier = [], threading.Barrier(4)

        def create(n, key=f"claims/{round_}", winners=winners, barrier=barrier):
            barrier.wait()
            if store.put_if(key, str(n).encode(), None) is not None:
                winners.append(n)

        threads = [threading.Thread(target=create, args=(n,)) for n in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
        assert len(winners) == 1 and store.get(f"claims/{round_}") == str(winners[0]).encode()


def test_event_log_numbers_events_and_the_cursor_reads_only_what_is_new(store):
    first = store.append_event("job/", {"type": "status", "status": "running"})
    assert first["seq"] == 1 and first["type"] == "status" and "time" in first
    store.append_event("job/", {"type": "iteration", "iteration": 0})
    events, cursor = store.read_events("job/")
    assert [e["seq"] for e in events] == [1, 2]
    assert [e["seq"] for e in store.read_events("job/", after=1)[0]] == [2]
    store.append_event("job/", {"type": "x"})
    more, cursor = store.read_events("job/", after=2, cursor=cursor)
    assert [e["seq"] for e in more] == [3]
    assert store.read_events("job/", after=3, cursor=cursor)[0] == []
    assert store.read_events("other/") == ([], store.read_events("other/")[1])


def test_concurrent_appenders_get_consecutive_numbers(store):
    threads = [threading.Thread(target=lambda: [store.append_event("j/", {"type": "x"}) for _ in range(15)])
               for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert [e["seq"] for e in store.read_events("j/")[0]] == list(range(1, 61))


def test_listing_deleting_and_the_keys_that_are_refused(store):
    for key in ("a/1/record.json", "a/2/record.json", "a/2/x.png", "a/10/r.json", "b/record.json"):
        store.put(key, b"x")
    assert list(store.keys("a/")) == ["a/1/record.json", "a/10/r.json", "a/2/record.json", "a/2/x.png"]
    assert list(store.keys("a/1")) == ["a/1/record.json", "a/10/r.json"]        # a string prefix
    assert list(store.keys("", delimiter=True)) == ["a/", "b/"]
    assert list(store.keys("a/", delimiter=True)) == ["a/1/", "a/10/", "a/2/"]
    assert store.prefix_bytes("a/2/") == 2
    assert store.delete_prefix("a/2/") == 2 and list(store.keys("a/")) == ["a/1/record.json", "a/10/r.json"]
    assert store.delete_prefix("a/1/record.json") == 1 and list(store.keys("a/")) == ["a/10/r.json"]
    assert store.delete_prefix("nothing/") == 0
    for bad in ("../x", "/etc/passwd", "a/../../x"):
        with pytest.raises(ValueError):
            store.get(bad)
        with pytest.raises(ValueError):
            store.delete_prefix(bad + "/")


def test_hidden_keys_are_not_listed(store):
    store.put(".idempotency/owner/abc", b"job")
    store.put("job/record.json", b"{}")
    assert list(store.keys("", delimiter=True)) == ["job/"]
    assert store.get(".idempotency/owner/abc") == b"job"


def test_delete_prefix_removes_the_event_log_and_numbering_restarts(store):
    store.append_event("job/", {"type": "x"})
    store.append_event("job/", {"type": "x"})
    store.put("job/record.json", b"{}")
    assert store.delete_prefix("job/") > 0 and list(store.keys("job/")) == []
    assert store.read_events("job/")[0] == []
    assert store.append_event("job/", {"type": "y"})["seq"] == 1


def test_open_streams_and_get_range_reads_a_slice(store):
    data = os.urandom(3 << 20)
    store.put("big/gradients.npy", data)
    handle = store.open("big/gradients.npy")
    with handle:
        parts = []
        while block := handle.read(1 << 16):
            assert len(block) <= 1 << 16
            parts.append(block)
    assert b"".join(parts) == data
    assert store.open("big/missing") is None
    assert store.get_range("big/gradients.npy", 1000, 50) == data[1000:1050]
    assert store.get_range("big/gradients.npy", len(data) - 10, 50) == data[-10:]
    assert store.get_range("big/missing", 0, 10) is None


def test_usage_bytes_counts_what_is_stored(store):
    store.put("a/x", b"12345")
    assert store.usage_bytes() >= 5


# ------------------------------------------------------------------------------ the folder store

def test_folder_atomic_write_leaves_the_old_object_when_the_write_fails(tmp_path, monkeypatch):
    store = FolderStore(tmp_path)
    store.put_json("job/record.json", {"a": 1})

    def boom(*args):
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", boom)
    with pytest.raises(OSError):
        store.put_json("job/record.json", {"a": 2})
    assert store.get_json("job/record.json") == {"a": 1}
    assert sorted(p.name for p in (tmp_path / "job").iterdir()) == ["record.json"]   # no temporary file left


def test_folder_event_log_skips_a_torn_line(tmp_path):
    store = FolderStore(tmp_path)
    store.append_event("job/", {"type": "status", "status": "running"})
    store.append_event("job/", {"type": "iteration", "iteration": 0})
    with (tmp_path / "job" / "events.jsonl").open("ab") as handle:
        handle.write(b'{"seq": 3, "type": "itera')                   # a writer killed mid-line
    events, cursor = store.read_events("job/")
    assert [e["seq"] for e in events] == [1, 2]
    with (tmp_path / "job" / "events.jsonl").open("ab") as handle:
        handle.write(b"\n")                                          # the torn line ends
    assert FolderStore(tmp_path).append_event("job/", {"type": "x"})["seq"] == 3   # numbering continues
    more, _ = store.read_events("job/", after=2, cursor=cursor)
    assert [e["seq"] for e in more] == [3]


def test_folder_a_full_disk_is_a_store_full_error(tmp_path, monkeypatch):
    store = FolderStore(tmp_path)

    def full(*args, **kwargs):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr("services.store.files.tempfile.mkstemp", full)
    with pytest.raises(StoreFull, match="full"):
        store.put("k", b"data")


# ---------------------------------------------------------------------------------- the S3 store

def _second_machine(store):
    """Another S3Store on the same bucket and prefix: another machine, with its own caches."""
    from harness.s3server import ACCESS_KEY, REGION, SECRET_KEY
    from services.store.s3 import S3Store

    return S3Store(store.url, endpoint=store.endpoint, access_key_id=ACCESS_KEY, secret_access_key=SECRET_KEY,
                   region=REGION)


def test_s3_events_are_one_object_each_under_ordered_keys(s3_store):
    for i in range(3):
        s3_store.append_event("job/", {"type": "iteration", "iteration": i})
    assert list(s3_store.keys("job/")) == [f"job/events/{n:012d}.json" for n in (1, 2, 3)]
    assert s3_store.get_json("job/events/000000000002.json")["iteration"] == 1


def test_s3_two_machines_append_to_one_log_without_losing_or_repeating_a_number(s3_store):
    other = _second_machine(s3_store)
    s3_store.append_event("job/", {"type": "a"})          # both machines now cache "1 exists"
    other.append_event("job/", {"type": "b"})             # takes 2
    third = s3_store.append_event("job/", {"type": "c"})  # 2 is taken: lists after 1, takes 3
    assert third["seq"] == 3
    threads = [threading.Thread(target=lambda s=s: [s.append_event("job/", {"type": "x"}) for _ in range(10)])
               for s in (s3_store, other, s3_store, other)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    events, _ = other.read_events("job/")
    assert [e["seq"] for e in events] == list(range(1, 44))
    other.close()


def test_s3_replay_lists_after_the_last_event_id(s3_store):
    for i in range(30):
        s3_store.append_event("job/", {"type": "iteration", "iteration": i})
    events, cursor = s3_store.read_events("job/", after=25)
    assert [e["seq"] for e in events] == [26, 27, 28, 29, 30] and cursor == 30
    assert s3_store.read_events("job/", after=0, cursor=cursor) == ([], 30)


def test_s3_objects_carry_their_content_type_and_presigned_urls_work(s3_store):
    from harness.s3server import ACCESS_KEY, REGION, SECRET_KEY
    from services.store.s3 import S3Store

    s3_store.put("job/iterations/000001/render.png", b"\x89PNG" + b"0" * 2000)
    assert s3_store.redirect_url("job/iterations/000001/render.png") is None    # off by default
    signing = S3Store(s3_store.url, endpoint=s3_store.endpoint, presign_bytes=1000, access_key_id=ACCESS_KEY,
                      secret_access_key=SECRET_KEY, region=REGION)
    s3_store.put("job/small.json", b"{}")
    assert signing.redirect_url("job/small.json") is None                       # under the threshold
    url = signing.redirect_url("job/iterations/000001/render.png")
    assert url is not None and "X-Amz-Signature=" in url
    with urllib.request.urlopen(url, timeout=10) as response:                   # no credentials needed
        assert response.headers["Content-Type"] == "image/png" and response.read()[:4] == b"\x89PNG"


def test_s3_usage_bytes_is_cached(s3_store):
    s3_store.put("a", b"1234")
    first = s3_store.usage_bytes()
    s3_store.put("b", b"5678")
    assert s3_store.usage_bytes() == first                  # reused within usage_ttl
    s3_store._usage = None
    assert s3_store.usage_bytes() == first + 4


def test_s3_names_are_s3_urls():
    from services.store.s3 import parse_url

    assert parse_url("s3://bucket/some/prefix/") == ("bucket", "some/prefix")
    assert parse_url("s3://bucket") == ("bucket", "")
    with pytest.raises(ValueError):
        parse_url("gs://bucket/x")


def test_s3_streams_a_large_object_in_chunks_not_whole(s3_store):
    data = np.arange(1 << 20, dtype=np.float32).tobytes()          # 4 MiB
    s3_store.put("job/iterations/000000/gradients.npy", data)
    handle = s3_store.open("job/iterations/000000/gradients.npy")
    assert isinstance(handle, io.BufferedReader)
    with handle:
        assert handle.read(16) == data[:16]
        assert len(handle.raw._pending) < len(data)               # the rest is not in memory yet
        assert handle.read() == data[16:]


def test_the_s3_client_is_imported_only_when_an_s3_store_is_configured(tmp_path):
    import subprocess
    import sys

    from harness.cluster import ROOT

    code = ("import sys; from services.settings import Settings; from services.runtime import open_store; "
            "import api.app, worker.main; open_store(Settings(store=sys.argv[1])); "
            "print(sorted(m for m in ('obstore', 'boto3', 's3fs', 'moto') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "runs")], capture_output=True, text=True,
                         check=True, cwd=ROOT).stdout
    assert out.strip() == "[]"
    out = subprocess.run([sys.executable, "-c", code, "s3://ndrf/x"], capture_output=True, text=True, check=True,
                         cwd=ROOT).stdout
    assert out.strip() == "['obstore']"

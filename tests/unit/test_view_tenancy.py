"""Views sized before their child starts, and warm view children that belong to a key (issue 38)."""

from __future__ import annotations

from types import SimpleNamespace

import pytest

from harness.cluster import small_job
from schemas.errors import InvalidJob
from schemas.job import JobSpec
from schemas.views import ViewRequest
from services.jobs.view_sessions import ViewSessions
from services.jobs.views import check_view
from services.settings import Limits


def test_a_view_is_sized_against_the_services_limits_before_it_starts():
    spec = JobSpec.model_validate(small_job("direct"))
    limits = Limits()
    check_view(ViewRequest(sensor=0, resolution=(256, 256), spp=16), spec, limits)            # 1 Mi samples: at the cap
    with pytest.raises(InvalidJob) as caught:        # the probe's 512 x 512 x 16 view peaked at 7.2 GiB
        check_view(ViewRequest(sensor=0, resolution=(512, 512), spp=16), spec, limits)
    assert caught.value.field == "spp" and "NDRF_MAX_VIEW_SAMPLES" in caught.value.message
    with pytest.raises(InvalidJob, match="NDRF_MAX_VIEW_SAMPLES") as caught:
        check_view(ViewRequest(sensor=0, resolution=(64, 64), prb_spp=4096), spec, limits)
    assert caught.value.field == "prb_spp"
    with pytest.raises(InvalidJob, match="NDRF_MAX_RESOLUTION"):
        check_view(ViewRequest(sensor=0, resolution=(300, 200)), spec, Limits(resolution=256))
    with pytest.raises(InvalidJob, match="NDRF_MAX_SPP"):
        check_view(ViewRequest(sensor=0, resolution=(16, 16), spp=32), spec, Limits(spp=16))


def test_one_key_cannot_evict_another_keys_only_warm_child():
    sessions = ViewSessions(60.0, 2)

    def held(owner: str, used: float):
        return SimpleNamespace(owner=owner, used=used)

    sessions.sessions = {("b1", "d"): held("bob", 1.0), ("a1", "d"): held("alice", 2.0)}
    assert sessions._evictable("alice") == ("a1", "d")         # alice makes room with her own
    sessions.sessions = {("b1", "d"): held("bob", 1.0), ("c1", "d"): held("carol", 2.0)}
    assert sessions._evictable("alice") is None                 # nobody's only child is taken: not kept
    sessions.sessions = {("b1", "d"): held("bob", 1.0), ("b2", "d"): held("bob", 3.0)}
    assert sessions._evictable("alice") == ("b1", "d")         # bob holds both: his older one goes


def test_a_warm_child_evicted_during_a_view_is_closed_after_it_not_under_it():
    import threading

    from services.jobs.view_sessions import ViewSession

    session = ViewSession.__new__(ViewSession)     # no child: its view and close are recorded
    session.lock, session.retired, session.closed = threading.Lock(), False, False
    closed_during: list[bool] = []

    def close():
        closed_during.append(in_flight[0])
        session.closed = True

    in_flight = [False]

    def answer(request, out):
        in_flight[0] = True
        session.retire()                          # another request evicts it meanwhile
        assert not session.closed                 # the child answering is not killed under the view
        in_flight[0] = False
        return "viewed", {}, {}

    session.close, session._view = close, answer
    assert session.view(None, None) == ("viewed", {}, {})
    assert closed_during == [False] and session.closed   # closed once the view let go of it

"""Mini-batches of views (``services/solver/optimize/views.py``): every view once per pass,
seeded, resumable from the stream position, scaled to the sum over views."""

from __future__ import annotations

import pytest

from services.solver.optimize.views import ViewStream


def _batches(stream, size, count, offset=0):
    out = []
    for _ in range(count):
        batch = stream.batch(offset, size)
        out.append(batch.sensors)
        offset = batch.offset
    return out, offset


def test_one_view_per_iteration_sees_every_view_once_per_pass():
    stream = ViewStream([3, 0, 5, 1], seed=7)
    batches, _ = _batches(stream, 1, 12)
    for p in range(3):
        assert sorted(v for b in batches[4 * p:4 * p + 4] for v in b) == [0, 1, 3, 5]
    assert [b[0] for b in batches[:4]] != [b[0] for b in batches[4:8]]  # a new order each pass (seeded)


def test_the_stream_is_seeded_and_resumes_from_its_position():
    a, _ = _batches(ViewStream(list(range(8)), seed=1), 2, 10)
    b, _ = _batches(ViewStream(list(range(8)), seed=1), 2, 10)
    c, _ = _batches(ViewStream(list(range(8)), seed=2), 2, 10)
    assert a == b and a != c
    first, offset = _batches(ViewStream(list(range(8)), seed=1), 2, 4)
    rest, _ = _batches(ViewStream(list(range(8)), seed=1), 2, 6, offset)   # a resumed run
    assert first + rest == a
    assert all(len(set(batch)) == 2 for batch in a)                       # distinct views


def test_scale_estimates_the_sum_over_views_and_a_full_batch_is_every_view():
    stream = ViewStream([2, 0, 1, 3], seed=0)
    assert stream.batch(5, 1).scale == 4.0 and stream.batch(5, 2).scale == 2.0
    full = stream.batch(5, 9)
    assert full.sensors == [0, 1, 2, 3] and full.scale == 1.0
    with pytest.raises(ValueError, match="at least one view"):
        stream.batch(0, 0)
    with pytest.raises(ValueError, match="target view"):
        ViewStream([], seed=0)

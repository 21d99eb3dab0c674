"""Views of a job's fields (``services/solver/optimize/field_views.py``, ``scene/cameras.py``): a
view from the job's own sensor shows what the loop's gradient images showed; a new camera gives
finite images of the right shapes; the scene rebuilt with a camera keeps keys and renders."""

from __future__ import annotations

import io
import json

import numpy as np
import pytest
import torch
from pydantic import ValidationError

from schemas.job import JobSpec
from schemas.views import ViewRequest
from tests.support.jobs import run_job, small_job


def _rel(a, b):
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


@pytest.fixture(scope="module")
def job(tmp_path_factory, mi):
    out = tmp_path_factory.mktemp("views") / "job"
    summary = run_job(small_job("ndrf-lhs", iterations=2, images_every=1), out)
    assert summary["status"] == "succeeded", summary
    spec = JobSpec.model_validate(json.loads((out / "spec.json").read_text()))
    return spec, (out / "checkpoints" / "latest.pt").read_bytes(), out


@pytest.fixture(scope="module")
def restored(job):
    from services.solver.optimize.field_views import restore

    spec, blob, _ = job
    return restore(spec, blob)


@pytest.mark.slow  # the module's job: ~25 s on 2 busy cores
def test_a_view_from_the_jobs_own_sensor_shows_the_loops_gradient_images(job, restored):
    """The loop's last gradient images (ndrf-lhs: dL_theta at its own camera samples, gradient_spp
    4) against the view from sensor 0 at 4 spp. They differ only by pixel samples, so the written
    tolerance is the noise between two views with different seeds (x1.5, + 0.02)."""
    from services.solver.optimize.field_views import render_view

    _, _, out = job
    last = sorted((out / "iterations").iterdir())[-1]
    loop = np.load(last / "gradients.npy")
    a = render_view(restored, ViewRequest(sensor=0, spp=4, seed=0))
    b = render_view(restored, ViewRequest(sensor=0, spp=4, seed=1))
    assert a.gradients.shape == loop.shape
    noise = _rel(a.gradients, b.gradients)
    assert _rel(a.gradients, loop) <= 1.5 * noise + 0.02, (_rel(a.gradients, loop), noise)
    assert np.abs(loop).max() > 0  # a test that can fail: the images are not all zero


@pytest.mark.slow  # the module's job: ~25 s on 2 busy cores
def test_a_new_camera_gives_finite_images_of_the_right_shapes(restored):
    from services.solver.optimize.field_views import render_view

    view = render_view(restored, ViewRequest(origin=(0.3, 0.2, 3.0), target=(0.0, 0.0, 0.0), fov=35,
                                             resolution=(24, 12), spp=2, prb_spp=4))
    p = restored.problem.parameters.n
    assert view.radiance.shape == (12, 24, 3) and view.gradients.shape == (p, 12, 24, 3)
    assert view.prb is not None and view.prb.shape == (p, 12, 24, 3)
    assert np.isfinite(view.radiance).all() and np.isfinite(view.gradients).all() and np.isfinite(view.prb).all()
    assert view.radiance.mean() > 0 and np.abs(view.gradients).max() > 0
    assert view.camera["resolution"] == [24, 12]


@pytest.mark.slow  # the module's job: ~25 s on 2 busy cores
def test_a_moved_sensor_sees_a_different_image(restored):
    from services.solver.optimize.field_views import render_view

    here = render_view(restored, ViewRequest(sensor=0, spp=2))
    moved = render_view(restored, ViewRequest(sensor=0, offset=(0.3, 0.0, 0.0), spp=2))
    assert _rel(moved.radiance, here.radiance) > 0.05


def test_the_scene_rebuilt_with_a_camera_keeps_keys_and_renders_its_sensors_alike(mi):
    from services.solver.scene.cameras import perspective, with_cameras
    from services.solver.scene.load import load_scene

    loaded = load_scene(builtin="cornell-box", resolution=(16, 16))
    rebuilt = with_cameras(loaded, [perspective((0, 0, 3), (0, 0, 0), (0, 1, 0), 40, 8, 8)])
    assert set(loaded.params.keys()) <= set(rebuilt.params.keys())
    assert rebuilt.sensor_count == loaded.sensor_count + 1 and rebuilt.resolution(1) == (8, 8)
    a = np.array(mi.render(loaded.scene, spp=8, sensor=0, seed=1))
    b = np.array(mi.render(rebuilt.scene, spp=8, sensor=0, seed=1))
    np.testing.assert_allclose(a, b, rtol=0, atol=1e-6)


def test_degenerate_cameras_are_refused(mi):
    from services.solver.scene.cameras import perspective

    with pytest.raises(ValueError, match="parallel"):
        perspective((0, 0, 3), (0, 0, 0), (0, 0, 1), 40, 8, 8)
    with pytest.raises(ValueError, match="coincide"):
        perspective((0, 0, 0), (0, 0, 0), (0, 1, 0), 40, 8, 8)


@pytest.mark.parametrize("body, message", [
    ({"origin": [0, 0, 3], "target": [0, 0, 0], "sensor": 0}, "not both"),
    ({"origin": [0, 0, 3]}, "both origin and target"),
    ({}, "give origin and target"),
    ({"origin": [0, 0, 3], "target": [0, 0, 0], "offset": [1, 0, 0]}, "offset moves a scene sensor"),
    ({"sensor": 0, "resolution": [1024, 16]}, "resolution"),
    ({"sensor": 0, "spp": 65}, "less than or equal to 64"),
    ({"sensor": 0, "prb_spp": 5000}, "less than or equal to 4096"),
])
def test_view_requests_out_of_range_are_refused(body, message):
    with pytest.raises(ValidationError, match=message):
        ViewRequest.model_validate(body)


@pytest.mark.slow  # the module's job: ~25 s on 2 busy cores
def test_a_checkpoint_of_another_job_or_without_fields_is_refused(job, tmp_path):
    from services.solver.optimize.field_views import restore

    spec, blob, _ = job
    with pytest.raises(ValueError, match="different job"):
        restore(spec.model_copy(update={"seed": spec.seed + 1}), blob)
    state = torch.load(io.BytesIO(blob), weights_only=True)
    state["trainer"]["layout"]["scalars"] = state["trainer"]["layout"]["scalars"][::-1]  # outputs read as others
    buffer = io.BytesIO()
    torch.save(state, buffer)
    with pytest.raises(ValueError, match="another layout"):
        restore(spec, buffer.getvalue())
    out = tmp_path / "prb"
    assert run_job(small_job("prb", iterations=1), out)["status"] == "succeeded"
    prb_spec = JobSpec.model_validate(json.loads((out / "spec.json").read_text()))
    with pytest.raises(ValueError, match="trained no field"):
        restore(prb_spec, (out / "checkpoints" / "latest.pt").read_bytes())

"""Geometry parameters (issue 34): a mesh's pose (``<shape>.to_world.translate`` / ``.rotate``),
what resolves it (Mitsuba's projective integrators; every other method refuses it), the XML a
user pastes back, the refusal of steps that break a mesh, the gradient against finite
differences and a recovery with Levenberg-Marquardt."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.solver.optimize.resolve import resolve
from services.solver.optimize.validate import check_geometry
from services.solver.scene.geometry import pose_matrix, refusal, rotation_matrix, split_key, transform_xml

POSE = ["block.to_world.translate", "block.to_world.rotate"]


def _spec(**extra) -> JobSpec:
    job = {"scene": {"builtin": "pose-block"}, "parameters": [{"key": key} for key in POSE],
           "targets": {"synthetic": {"values": {POSE[0]: [0.04, 0.0, -0.03], POSE[1]: [0.0, 10.0, 0.0]}}}}
    return JobSpec.model_validate({**job, **extra})


class Measures:
    """What resolve may measure, faked: the share of the light beyond direct illumination."""

    def __init__(self, missing: float = 0.05):
        self.missing = missing

    def facts(self):
        raise AssertionError("geometry takes no effect probe")

    def closure(self):
        return 0.1

    def direct(self):
        return [True] * 6

    def missing_energy(self, depth):
        return self.missing

    def footprint(self, key, shape):
        raise AssertionError("no texture")

    def film(self):
        return (64, 48)


def _parameters():
    return SimpleNamespace(has_textures=False, has_geometry=True, n=6, sizes=[3, 3], geometry=[True] * 6,
                           step_units=lambda: np.array([1.0] * 3 + [180.0] * 3), shape_spans=lambda: [],
                           flat_meshes=lambda: [])


def test_keys_and_matrices():
    assert split_key("bunny.to_world.rotate") == ("bunny", "to_world.rotate")
    assert split_key("red.reflectance.value") is None
    # about x, then y, then z: R = Rz Ry Rx
    np.testing.assert_allclose(rotation_matrix([90, 0, 0]) @ [0, 1, 0], [0, 0, 1], atol=1e-12)
    np.testing.assert_allclose(rotation_matrix([90, 90, 0]) @ [0, 1, 0], [1, 0, 0], atol=1e-12)
    centre = np.array([1.0, 2.0, 3.0])
    matrix = pose_matrix([0.1, 0, 0], [0, 30, 0], centre)
    np.testing.assert_allclose(matrix[:3, :3] @ centre + matrix[:3, 3], centre + [0.1, 0, 0], atol=1e-12)


@pytest.mark.parametrize("method", ["ndrf-lhs", "ndrf-rhs", "radiance-cache", "direct", "prb"])
def test_methods_without_a_boundary_term_refuse_geometry_with_the_reason(method):
    """Refused by the validate stage, before resolve decides anything (resolve raises nothing)."""
    with pytest.raises(InvalidJob, match="boundary term for moving silhouettes") as raised:
        check_geometry(_spec(method=method), geometry=True, mesh_scalars=0)
    assert raised.value.field == "method"
    with pytest.raises(InvalidJob, match="dL_theta's, which has no boundary term") as raised:
        check_geometry(_spec(method="prb-projective", jacobian="differential-field"), geometry=True, mesh_scalars=0)
    assert raised.value.field == "jacobian"
    check_geometry(_spec(method="prb-projective"), geometry=True, mesh_scalars=0)
    check_geometry(_spec(method=method), geometry=False, mesh_scalars=0)   # no shape moves: any method


def test_auto_takes_a_projective_integrator_and_levenberg_marquardt_with_every_channel():
    recipe = resolve(_spec(), _parameters(), 2, Measures(missing=0.05))
    assert recipe.method == "prb-projective" and recipe.steps.optimizer == "levenberg-marquardt"
    assert recipe.layout.channels == ((0, 1, 2),) * 6   # a translation is not an RGB value
    assert recipe.batch.views == 2 and recipe.batch.spp == 16
    assert recipe.step_units[3] == 180.0
    reasons = {d.what: d.reason for d in recipe.decisions}
    assert "5.00% of the image's light" in reasons["method"]
    assert resolve(_spec(), _parameters(), 2, Measures(missing=0.0)).method == "direct-projective"
    own = resolve(_spec(method="direct-projective", optimizer="adam"), _parameters(), 2, Measures())
    assert own.method == "direct-projective" and own.steps.optimizer == "adam"


def test_a_step_that_breaks_the_mesh_is_refused_with_the_reason():
    vertices = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], float)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    assert refusal(vertices, vertices + 0.3, faces) is None
    flipped = vertices.copy()
    flipped[2] = [0, -1, 0]                     # the first triangle turns over
    assert refusal(vertices, flipped, faces) == "inverted triangles"
    broken = vertices.copy()
    broken[1, 0] = np.nan
    assert refusal(vertices, broken, faces) == "non-finite vertices"


def test_the_pasted_transform_is_the_pose_mitsuba_loads(mi):
    """The XML of a pose, pasted after a shape's own to_world, moves its vertices where the run
    moved them; the element alone loads as the pose's matrix."""
    translate, rotate = np.array([0.1, -0.2, 0.05]), np.array([10.0, -25.0, 40.0])
    own = '<scale value="0.3, 0.15, 0.2"/><translate value="0, 0.15, 0"/>'

    def cube(transform: str):
        scene = mi.load_string(f'<scene version="3.0.0"><shape type="cube" id="box">'
                               f'<transform name="to_world">{transform}</transform></shape></scene>')
        return np.array(mi.traverse(scene)["box.vertex_positions"], np.float64).reshape(-1, 3)

    loaded = cube(own)
    centre = (loaded.min(axis=0) + loaded.max(axis=0)) / 2
    xml = transform_xml(translate, rotate, centre)
    pasted = xml.split("\n", 2)[2].rsplit("\n", 1)[0]      # the operations, without the element's tags
    matrix = pose_matrix(translate, rotate, centre)
    np.testing.assert_allclose(cube(own + pasted), loaded @ matrix[:3, :3].T + matrix[:3, 3], atol=2e-5)
    sensor = mi.load_string(f'<sensor type="perspective" version="3.0.0">{xml}</sensor>')
    np.testing.assert_allclose(np.array(sensor.world_transform().matrix, np.float64).reshape(4, 4), matrix,
                               atol=2e-5)


def test_a_pose_key_of_an_unknown_shape_is_refused(mi):
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="pose-block", resolution=(8, 8))
    with pytest.raises(ValueError, match="'nothing' is not a mesh"):
        ParameterSet(scene.params, ["nothing.to_world.translate"])
    parameters = ParameterSet(scene.params, POSE)
    assert parameters.n == 6 and parameters.values().tolist() == [0.0] * 6
    assert parameters.refuse(np.zeros(6), np.array([0, np.inf, 0, 0, 0, 0.0])) == "block: non-finite vertices"
    assert parameters.refuse(np.zeros(6), np.array([0.1, 0, 0, 0, 30, 0.0])) is None
    report = parameters.pose_reports(np.array([0.1, 0, 0, 0, 30, 0.0]))[0]
    assert report["shape"] == "block" and len(report["matrix"]) == 4 and "<rotate y=\"1\" angle=\"30\"/>" in report["xml"]


@pytest.mark.slow
def test_the_pose_gradient_matches_finite_differences(mi):
    """The Jacobian of a translation and of a rotation (``direct-projective``'s forward-mode
    images, 64 spp, two seeds averaged) projected on central differences of renders at 2048 spp:
    ``<J, D> / <D, D>`` between 0.3 and 1.25. Measured at 24x24: 0.66 for the translation and
    0.43 for the rotation (Mitsuba's own forward mode, without the product, gave 0.64 for the
    translation; 0.92-0.97 at 32x32 in another view of the block): the boundary term at this
    resolution falls short of the differences, an open question (docs/guide/geometry.md). The
    test failed at 0.15 / 0.07 when a pose's Jacobian kept one channel per component. (The
    projection, not ``Σ w · J`` for fixed weights: a block's moving edges brighten and darken the
    image alike, and such a sum is a small difference of noisy boundary terms.)"""
    import drjit as dr

    from services.solver.estimators.methods import make_method
    from services.solver.estimators.problem import Problem
    from services.solver.estimators.render import UNBIASED
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="pose-block", resolution=(24, 24))
    problem = Problem(scene, ParameterSet(scene.params, POSE))
    method = make_method("direct-projective", None, UNBIASED)
    jacobian = np.mean([method.gradient_images(problem, None, spp=64, seed=seed) for seed in range(2)], axis=0)
    ratios = {}
    for index, h in ((0, 0.02), (4, 2.0)):      # translate x (scene units), rotate y (degrees)
        images = []
        for sign in (1, -1):
            p = np.zeros(6)
            p[index] = sign * h
            problem.parameters.assign(p)
            with dr.suspend_grad():
                images.append(np.array(mi.render(scene.scene, integrator=method.integrator, spp=2048, seed=7),
                                       np.float64)[..., :3])
        problem.parameters.assign(np.zeros(6))
        finite = (images[0] - images[1]) / (2 * h)
        ratios[index] = float((jacobian[index] * finite).sum() / (finite * finite).sum())
    assert all(0.3 < ratio < 1.25 for ratio in ratios.values()), ratios


@pytest.mark.slow
def test_levenberg_marquardt_recovers_a_pose(tmp_path):
    """The default job on ``pose-block`` at 24x24 (``auto``: ``prb-projective``, Levenberg-Marquardt
    on a forward-mode Jacobian; at 16x16 its steps are noise-dominated, bench.geometry): within 12
    iterations the translation error is at least halved (Euclidean, from 0.05) and the rotation
    about the vertical axis has moved towards its 10 degrees; the answer is written as a 4x4 matrix
    and XML in final/poses.json and the summary. Not asserted, because it does not hold: the whole
    rotation. Measured: [-3.6, 4.9, 10.0] degrees for [0, 10, 0] (a tilt about z traded for the
    turn about y, at 24x24 from two views; 5.2 degrees off after 8 iterations, 7.6 after 12)."""
    import json

    from tests.support.jobs import run_job

    job = _spec(iterations=12, render={"resolution": [24, 24]},
                targets={"synthetic": {"values": {POSE[0]: [0.04, 0.0, -0.03], POSE[1]: [0.0, 10.0, 0.0]},
                                       "spp": 64}}, seed=1).model_dump(exclude_unset=True)
    summary = run_job(job, tmp_path)
    assert summary["status"] == "succeeded", summary.get("error")
    final, target = np.array(summary["estimate"]), np.array(summary["target_values"])
    assert np.linalg.norm(final[:3] - target[:3]) < 0.05 / 2
    assert abs(final[4] - target[4]) < 10.0, final.tolist()
    poses = json.loads((tmp_path / "final" / "poses.json").read_text())
    assert poses == summary["poses"] and poses[0]["shape"] == "block"
    # the dashboard's silhouettes, with the last iteration's images: both colours drawn
    from PIL import Image

    from services.solver.scene.silhouettes import CURRENT, TARGET

    for name in ("silhouette.png", "silhouette-1.png"):
        pixels = np.asarray(Image.open(tmp_path / "iterations" / f"{11:06d}" / name)).reshape(-1, 3) / 255.0
        assert np.any(np.all(np.abs(pixels - TARGET) < 0.01, axis=1)), name        # the target's outline
        tint = (pixels - pixels.mean(1, keepdims=True)) @ (CURRENT - CURRENT.mean())
        assert np.any(tint > 0.05), name                                         # the block now


def test_an_older_job_file_s_projective_method_name_reads_as_today_s():
    """One spelling per method (#45): ``prb-projective``, as ``ndrf-lhs``; a job file or job folder
    of an older version says ``prb_projective`` and still loads. Failed before the alias (the
    older name is no member of Method)."""
    from schemas.job import JobSpec

    old = {"scene": {"builtin": "pose-block"}, "method": "prb_projective",
           "parameters": [{"key": "block.to_world.translate", "init": [0.0, 0.0, 0.0]}],
           "targets": {"synthetic": {"values": {"block.to_world.translate": [0.1, 0.0, 0.0]}}}}
    assert JobSpec.model_validate(old).method == "prb-projective"
    assert JobSpec.model_validate({**old, "method": "direct_projective"}).method == "direct-projective"

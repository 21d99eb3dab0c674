"""Texture parameters (a bitmap's ``data``): prb's gradient per texel against finite differences,
the reports (records keep summaries, never every texel; the recovered texture as files), the
per-texel limit and the methods and optimizers that refuse a texture job with the reason
(``direct`` and ``radiance-cache`` carry one: ``tests/unit/test_texture_direct.py``).

The gradient check: a 4 x 4 RGB albedo on the back wall of the textured box (16 x 16 film, fixed
path depth 6, no Russian roulette). dz/dp of ``z = Σ w · y`` (``w`` a fixed random weight image)
from ``prb`` at 1024 spp against central differences of the path-traced ``z`` at p ± h (h = 0.1,
common random numbers: same seed on both sides, 1024 spp). The image is nearly linear in a texel
(direct light is linear; interreflection adds a small quadratic part that the central difference
cancels), so the two agree up to Monte Carlo noise of the adjoint's independent paths.
Tolerance: 5% of the largest of the compared entries (measured: about 1%).
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec

KEY = "wall.reflectance.data"


def _job(**changes) -> JobSpec:
    job = {"scene": {"builtin": "textured-box"}, "parameters": [{"key": KEY, "init": 0.5}],
           "targets": {"synthetic": {"values": {KEY: None}, "spp": 16}}, "iterations": 3,
           "render": {"resolution": [16, 16]}}
    job.update(changes)
    return JobSpec.model_validate(job)


def _read_exr(mi, path) -> np.ndarray:
    """An ``.exr`` the job wrote, as Mitsuba's OpenEXR reader decodes it (``(H, W, C)`` float32)."""
    bitmap = mi.Bitmap(str(path))
    assert bitmap.component_format() == mi.Struct.Type.Float32
    pixels = np.array(bitmap, copy=True)
    return pixels.reshape(*pixels.shape[:2], -1)


def test_prb_texel_gradient_matches_central_differences(mi):
    from services.solver.estimators.methods import Fields
    from services.solver.estimators.methods.prb import Prb
    from services.solver.estimators.problem import Problem
    from services.solver.estimators.render import PathDepth, render
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet
    from services.solver.scene.textured import textured_box

    scene = load_scene(mitsuba_dict=textured_box(size=4, views=1, film=16))
    params = ParameterSet(scene.params, [KEY])
    assert params.n == 48 and params.infos[0].shape == (4, 4, 3)
    problem, depth = Problem(scene, params), PathDepth(6, None)
    w = np.random.default_rng(0).uniform(0.5, 1.5, (16, 16, 3)).astype(np.float32)
    adjoint = Prb(depth=depth).loss_gradient(problem, Fields(), w, spp=1024, seed=3)
    p0, h = params.values(), 0.1
    texels = [0 * 3 + 0, 5 * 3 + 1, 10 * 3 + 2, 15 * 3 + 0]   # texel (row, col, channel): (0,0,R) (1,1,G) (2,2,B) (3,3,R)
    central = []
    for i in texels:
        z = []
        for sign in (1, -1):
            p = p0.copy()
            p[i] += sign * h
            params.assign(p)
            z.append(float(np.sum(render(problem, spp=1024, seed=11, depth=depth) * w)))
        central.append((z[0] - z[1]) / (2 * h))
    params.assign(p0)
    ours = adjoint[texels]
    scale = max(np.max(np.abs(central)), 1e-6)
    assert np.all(np.abs(ours - np.asarray(central)) <= 0.05 * scale), (ours, central)
    assert np.min(np.abs(central)) > 0.05 * scale   # every compared texel is seen: a real check


def test_texture_job_reports_summaries_and_files(mi, tmp_path):
    from services.jobs.local import run_local
    from services.solver.scene.textured import true_albedo

    spec = _job(images_every=2)
    events: list[dict] = []
    summary = run_local(spec, tmp_path / "job", on_event=events.append)
    assert summary["status"] == "succeeded", summary
    preparing = [e["what"] for e in events if e["type"] == "preparing"]   # said before the plan, not "starting"
    assert preparing == ["loading and checking the scene", "rendering 4 synthetic target(s) at 16 spp"]
    assert [e["type"] for e in events].index("plan") > [e["type"] for e in events].index("preparing")
    files = {"npy": f"final/{KEY}.npy", "exr": f"final/{KEY}.exr", "png": f"final/{KEY}.png",
             "target": f"final/{KEY}.target.npy", "target_exr": f"final/{KEY}.target.exr",
             "last": f"final/{KEY}.last.npy", "last_exr": f"final/{KEY}.last.exr", "last_png": f"final/{KEY}.last.png"}
    errors = {"standard_error": f"final/{KEY}.standard_error.npy", "standard_error_exr": f"final/{KEY}.standard_error.exr",
              "standard_error_png": f"final/{KEY}.standard_error.png"}
    assert summary["textures"][KEY] in (files, files | errors)   # the answer, the last iterate, its error map
    target = np.load(tmp_path / "job" / summary["textures"][KEY]["target"])
    assert np.allclose(target, true_albedo())
    final = np.load(tmp_path / "job" / summary["textures"][KEY]["npy"])
    assert final.shape == (64, 64, 3) and final.dtype == np.float32
    for npy, exr in ((summary["textures"][KEY]["npy"], summary["textures"][KEY]["exr"]),
                     (summary["textures"][KEY]["target"], summary["textures"][KEY]["target_exr"])):
        assert np.array_equal(_read_exr(mi, tmp_path / "job" / exr), np.load(tmp_path / "job" / npy))
    assert not np.allclose(final, 0.5)                       # it moved from the initial grey
    plan = json.loads((tmp_path / "job" / "plan.json").read_text())
    assert plan["scalars"] == [] and plan["textures"][0]["shape"] == [64, 64, 3]
    assert plan["textures"][0]["init"]["mean"] == [0.5, 0.5, 0.5]
    assert plan["recipe"]["optimizer"] == "adam" and plan["method"] == "prb"
    record = json.loads((tmp_path / "job" / "iterations" / "000002" / "record.json").read_text())
    assert record["parameters"] == [] and record["dz_dp"] == []
    texture = record["textures"][KEY]
    assert set(texture) >= {"mean", "min", "max", "gradient_rms", "rmse", "psnr"}
    assert 0.0 < texture["psnr"] < 60.0 and texture["gradient_rms"] > 0.0
    written = tmp_path / "job" / "iterations" / "000002" / "textures"
    assert np.load(written / f"{KEY}.dz_dp.npy").shape == (64, 64, 3)    # the gradient is a texture
    for name in (KEY, f"{KEY}.dz_dp"):                                       # each snapshot has its .exr
        assert np.array_equal(_read_exr(mi, written / f"{name}.exr"), np.load(written / f"{name}.npy"))
    assert (written / f"{KEY}.png").stat().st_size > 0
    assert not list((tmp_path / "job" / "iterations" / "000002").glob("gradient*"))   # never P images


def test_texture_init_per_channel_and_target_from_scene(mi):
    from services.solver.optimize.setup import check
    from services.solver.scene.textured import true_albedo

    checked = check(_job(parameters=[{"key": KEY, "init": [0.2, 0.4, 0.6], "bounds": [0.1, 0.9]}]))
    assert np.allclose(checked.init.reshape(64, 64, 3), [0.2, 0.4, 0.6])
    assert np.allclose(checked.lower, 0.1) and np.allclose(checked.upper, 0.9)
    assert checked.target_values is not None
    assert np.allclose(checked.target_values.reshape(64, 64, 3), true_albedo(), atol=1e-6)
    assert checked.report()["texels"] == 4096 and checked.report()["scalars"] == 0


def test_texel_limit_refuses_and_scalar_limit_ignores_textures(mi):
    from services.solver.optimize.setup import check

    with pytest.raises(InvalidJob, match="4096 texels, more than the limit of 1000 .*NDRF_MAX_TEXELS"):
        check(_job(), max_texels=1000)
    check(_job(), max_scalars=3, max_texels=4096)        # 12,288 scalars, all in the texture


@pytest.mark.parametrize("change, field, reason", [
    ({"method": "ndrf-lhs"}, "method", "dL_theta has three outputs per scalar"),
    ({"method": "ndrf-rhs"}, "method", "set training.head for the many-parameter head"),
    ({"optimizer": "levenberg-marquardt"}, "optimizer", r"P x P curvature \(1.1 GiB\)"),
    ({"optimizer": "gauss-newton"}, "optimizer", "P x P curvature"),
    ({"jacobian": "differential-field"}, "jacobian", "dL_theta"),
])
def test_methods_that_cannot_carry_a_texture_are_refused(mi, change, field, reason):
    from services.solver.optimize.setup import check

    with pytest.raises(InvalidJob, match=reason) as refused:
        check(_job(**change))
    assert refused.value.field == field


def test_jobs_without_textures_keep_every_scalar_listed(mi):
    from services.solver.optimize.textures import TextureReport
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    scene = load_scene(builtin="textured-box", resolution=(8, 8))
    both = TextureReport(ParameterSet(scene.params, ["red.reflectance.value", KEY]))
    assert both.labels == ["red.reflectance.value[0]", "red.reflectance.value[1]", "red.reflectance.value[2]"]
    flat = np.arange(3 + 12288, dtype=np.float64)
    assert both.scalars(flat) == [0.0, 1.0, 2.0]
    assert both.images(flat)[KEY][0, 0].tolist() == [3.0, 4.0, 5.0]
    plain = TextureReport(ParameterSet(scene.params, ["red.reflectance.value"]))
    assert not plain and plain.scalars(flat[:3]) == [0.0, 1.0, 2.0]


@pytest.mark.parametrize("kind", ["laplacian", "tv"])
def test_smoothness_gradient_matches_finite_differences_of_the_penalty(kind):
    """The penalty's gradient against central differences of the penalty itself (h = 1e-6;
    tolerance 1e-6 relative to the largest entry: float64, a smooth function)."""
    from services.solver.optimize.regularize import TV_EPSILON, smoothness_gradient

    t = np.random.default_rng(1).uniform(0, 1, (3, 4, 2))

    def penalty(x):
        diffs = np.concatenate([np.diff(x, axis=0).ravel(), np.diff(x, axis=1).ravel()])
        terms = diffs ** 2 if kind == "laplacian" else np.sqrt(diffs ** 2 + TV_EPSILON ** 2)
        return 2.5 * terms.mean()

    analytic = smoothness_gradient(t, kind, 2.5)
    numeric = np.zeros_like(t)
    for index in np.ndindex(t.shape):
        up, down = t.copy(), t.copy()
        up[index] += 1e-6
        down[index] -= 1e-6
        numeric[index] = (penalty(up) - penalty(down)) / 2e-6
    assert np.max(np.abs(analytic - numeric)) <= 1e-6 * np.max(np.abs(numeric))


def test_coarse_to_fine_pools_the_gradient_in_blocks_then_lets_go():
    from schemas.job import TextureSettings
    from services.solver.optimize.regularize import block_size, pooled

    settings = TextureSettings(coarse_to_fine=2)
    assert [block_size(settings, k, 8) for k in range(8)] == [4, 4, 2, 2, 1, 1, 1, 1]
    assert block_size(TextureSettings(), 0, 8) == 1
    g = np.arange(5 * 5 * 1, dtype=np.float64).reshape(5, 5, 1)
    out = pooled(g, 2)
    assert out[0, 0, 0] == out[1, 1, 0] == np.mean(g[:2, :2]) and out[4, 4, 0] == g[4, 4, 0]
    assert np.allclose(out[:4, :4].reshape(2, 2, 2, 2).std(axis=(1, 3)), 0.0)


def test_texture_reports_cross_the_sandbox_pipe():
    """What the sandboxed child sends (PipeReporter) is what the parent's writer receives."""
    import io

    from services.jobs.child import PipeReporter
    from services.jobs.frames import read_frame
    from services.jobs.runner import AttemptRunner

    class Writer:
        got: list = []

        def textures(self, iteration, images):
            self.got.append((iteration, images))

    stream = io.BytesIO()
    value = np.random.default_rng(2).uniform(0, 1, (5, 7, 3)).astype(np.float32)
    PipeReporter(stream).textures(4, {KEY: value, f"{KEY}.dz_dp": -value})
    PipeReporter(stream).textures(None, {KEY: value})
    stream.seek(0)
    writer = Writer()
    while (frame := read_frame(stream)) is not None:
        AttemptRunner._dispatch(writer, *frame)   # type: ignore[arg-type]
    assert [g[0] for g in writer.got] == [4, None]
    assert np.array_equal(writer.got[0][1][f"{KEY}.dz_dp"], -value) and np.array_equal(writer.got[1][1][KEY], value)


def test_per_scalar_gradient_images_of_a_texture_job_are_refused(mi):
    from services.solver.optimize.evaluate import evaluate_gradient

    with pytest.raises(InvalidJob, match="one per scalar, 12288 for a texture job"):
        evaluate_gradient(_job(method="prb"), "prb", spp=1)


def test_auto_gives_a_texture_job_every_view_and_16_spp_unless_set():
    from types import SimpleNamespace

    import numpy as np

    from services.solver.optimize.resolve import TEXTURE_SPP, resolve

    parameters = SimpleNamespace(has_textures=True, has_geometry=False, n=48, sizes=[48],
                                 textures=[("wall.reflectance.data", (4, 4, 3))])
    measures = SimpleNamespace(closure=lambda: None, direct=lambda: [False] * 48,   # never asked for a texture
                               footprint=lambda key, shape: np.full(shape[:2], 10))

    def choose(spec):
        return resolve(spec, parameters, 4, measures)   # type: ignore[arg-type]

    recipe = choose(_job())
    assert (recipe.method, recipe.steps.optimizer, recipe.batch.views, recipe.batch.spp, recipe.batch.gradient_spp) == (
        "prb", "adam", 4, TEXTURE_SPP, TEXTURE_SPP)
    assert not recipe.batch.grows and any("every view" in d.reason for d in recipe.decisions)
    mine = choose(_job(render={"resolution": [16, 16], "spp": 2}))
    assert (mine.batch.views, mine.batch.spp, mine.batch.gradient_spp) == (4, 2, 1)
    chosen = choose(_job(views_per_iteration=2))
    assert (chosen.batch.views, chosen.batch.spp) == (2, 1)
    assert recipe.texture_blocks == (("wall.reflectance.data", 1),)                  # 10 pixels per texel: its own


def test_a_texture_whose_pixels_cannot_pin_its_texels_moves_in_blocks_matched_to_its_footprint():
    from types import SimpleNamespace

    import numpy as np

    from services.solver.optimize.resolve import PIXELS_PER_TEXEL, resolve

    parameters = SimpleNamespace(has_textures=True, has_geometry=False, n=64 * 64 * 3, sizes=[64 * 64 * 3],
                                 textures=[("wall.reflectance.data", (64, 64, 3))])
    counts = np.zeros((64, 64), int)
    counts[::2, ::2] = 3           # 0.75 pixels per texel; 4 x 4 blocks see 12 each, 2 x 2 blocks 3
    measures = SimpleNamespace(closure=lambda: None, direct=lambda: [], footprint=lambda key, shape: counts)
    recipe = resolve(_job(), parameters, 4, measures)   # type: ignore[arg-type]
    assert recipe.texture_blocks == (("wall.reflectance.data", 4),)
    said = {d.what: d for d in recipe.decisions}["resolution wall.reflectance.data"]
    assert said.value == "16x16" and f"fewer than {PIXELS_PER_TEXEL} pixels per texel" in said.reason
    full = resolve(_job(textures={"resolution": "full"}), parameters, 4, measures)   # type: ignore[arg-type]
    assert full.texture_blocks == (("wall.reflectance.data", 1),)


def test_scene_description_gives_a_texture_its_shape_and_mean(mi):
    import io

    from services.jobs.child import describe
    from services.jobs.frames import read_frame

    out = io.BytesIO()
    describe({"scene": {"builtin": "textured-box"}}, out)
    out.seek(0)
    kind, meta, _ = read_frame(out)
    assert kind == "described"
    wall = next(p for p in meta["scene"]["parameters"] if p["key"] == KEY)
    assert wall["shape"] == [64, 64, 3] and wall["size"] == 12288 and len(wall["value"]) == 3
    red = next(p for p in meta["scene"]["parameters"] if p["key"] == "red.reflectance.value")
    assert red["shape"] is None and len(red["value"]) == 3


def test_an_interrupted_texture_job_resumes_to_the_same_texture(mi, tmp_path):
    """The checkpoint holds every texel and Adam's moments for each: a run interrupted after a few
    iterations and resumed ends with the uninterrupted run's texture (tolerance: 1e-6, float32
    renders in one process)."""
    from services.jobs.local import run_local

    spec = _job(iterations=6, checkpoint_every=2, seed=3)
    reference = run_local(spec, tmp_path / "whole")
    calls = {"n": 0}

    def stop() -> str | None:
        calls["n"] += 1
        return "interrupted" if calls["n"] > 3 else None   # polled once per iteration (no fields to train)

    assert run_local(spec, tmp_path / "cut", should_stop=stop)["status"] == "interrupted"
    assert not (tmp_path / "cut" / "final" / f"{KEY}.npy").exists()          # written at the end only
    resumed = run_local(spec, tmp_path / "cut", resume=True)
    assert resumed["status"] == reference["status"] == "succeeded"
    np.testing.assert_allclose(np.load(tmp_path / "cut" / resumed["textures"][KEY]["npy"]),
                               np.load(tmp_path / "whole" / reference["textures"][KEY]["npy"]), atol=1e-6)


def test_an_uploaded_scene_s_files_travel_to_the_child_as_blobs():
    """A frame header holds 16 MiB; an upload may hold 64 MiB of files (a large EXR texture)."""
    import io

    from services.jobs.frames import MAX_HEADER_BYTES, read_frame, start_frame, started, write_frame

    big = "A" * (MAX_HEADER_BYTES + 1000)   # base64 of a file larger than a header
    start = {"spec": {"scene": {"xml": "<scene/>", "files": {"albedo.exr": big, "b.obj": "QQ=="}}}, "scene_file": "x"}
    stream = io.BytesIO()
    write_frame(stream, "start", *start_frame(start))
    stream.seek(0)
    kind, meta, blobs = read_frame(stream)
    assert kind == "start" and started(meta, blobs) == start
    builtin = {"spec": {"scene": {"builtin": "cornell-box"}}}
    assert start_frame(builtin) == (builtin, {})


def test_the_footprint_counts_the_pixels_that_see_each_texel(mi):
    """The textured box's back wall fills the middle of each view: at 32x32 pixels per view, its
    64x64 texels are seen by fewer pixels than they number, at 128x128 by more; a shape no camera
    sees has an empty footprint."""
    from services.solver.scene.footprint import pixels_per_texel, texel_footprint
    from services.solver.scene.load import load_scene

    small = texel_footprint(load_scene(builtin="textured-box", resolution=(32, 32)), "wall.reflectance.data",
                            (64, 64, 3), [0, 1, 2, 3])
    large = texel_footprint(load_scene(builtin="textured-box", resolution=(128, 128)), "wall.reflectance.data",
                            (64, 64, 3), [0, 1, 2, 3])
    assert small.shape == (64, 64) and 0 < small.sum() < 64 * 64 < large.sum()
    assert large.sum() == pytest.approx(16 * small.sum(), rel=0.05)      # 16x the pixels, the same share of them
    assert pixels_per_texel(small) < 1 <= pixels_per_texel(small, 4)
    assert (large > 0).mean() > 0.95                                     # every view sees the whole wall
    assert not texel_footprint(load_scene(builtin="textured-box", resolution=(32, 32)), "nothing.reflectance.data",
                               (8, 8, 3), [0]).any()

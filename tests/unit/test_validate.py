"""The validate stage (``services/solver/optimize/validate.py``): everything the schema alone
cannot see is raised by ``setup.check`` (the service's preflight and every run), before
``resolve``, which only chooses."""

from __future__ import annotations

import ast
from pathlib import Path
from types import SimpleNamespace

import pytest

from schemas.errors import InvalidJob
from schemas.job import JobSpec
from services.solver.scene.effects import EffectChoice, Effects, ScalarEffect

ROOT = Path(__file__).resolve().parents[2]
#: The modules of ``resolve``: its rules choose and explain, and raise nothing.
RESOLVE = ["services/solver/optimize/resolve.py", "services/solver/optimize/blur.py",
           "services/solver/optimize/stopping.py",
           *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "services/solver/optimize/rules").glob("*.py"))]
POSE = ["block.to_world.translate", "block.to_world.rotate"]


def _pose_job(**extra) -> JobSpec:
    job = {"scene": {"builtin": "pose-block"}, "parameters": [{"key": key} for key in POSE],
           "targets": {"synthetic": {"values": {POSE[0]: [0.04, 0.0, -0.03], POSE[1]: [0.0, 10.0, 0.0]}}}}
    return JobSpec.model_validate({**job, **extra})


def _albedo_job(**extra) -> JobSpec:
    job = {"scene": {"builtin": "room-open-8"},
           "parameters": [{"key": "walls.reflectance.value"}, {"key": "ball.reflectance.value"}],
           "targets": {"synthetic": {"values": {"walls.reflectance.value": 0.8, "ball.reflectance.value": 0.3}}}}
    return JobSpec.model_validate({**job, **extra})


@pytest.mark.parametrize("module", RESOLVE)
def test_resolve_raises_nothing(module):
    """A rule of resolve that refuses would refuse at run time what the preflight accepted."""
    tree = ast.parse((ROOT / module).read_text())
    raised = [node.lineno for node in ast.walk(tree) if isinstance(node, ast.Raise)]
    assert raised == [], f"{module} raises at lines {raised}: move the check to services/solver/optimize/validate.py"


def test_the_preflight_refuses_what_only_the_run_refused_before(mi):
    """``setup.check`` (what the service's preflight runs at submission) refuses a pose with a
    method that has no boundary term, dL_theta's Jacobian for a pose, and dL_theta's Jacobian
    with dL_theta turned off; a valid pose job passes."""
    from services.solver.optimize.setup import check

    with pytest.raises(InvalidJob, match="boundary term") as raised:
        check(_pose_job(method="prb"))
    assert raised.value.field == "method"
    with pytest.raises(InvalidJob, match="no boundary term") as raised:
        check(_pose_job(jacobian="differential-field"))
    assert raised.value.field == "jacobian"
    check(_pose_job(method="prb-projective"))
    with pytest.raises(InvalidJob, match="effects.differential_field") as raised:
        check(_albedo_job(jacobian="differential-field", effects={"differential_field": "off"}))
    assert raised.value.field == "jacobian"


def test_a_scene_without_interreflection_takes_the_methods_own_jacobian(monkeypatch):
    """Where the scene (not the job) turns dL_theta off, the hybrid's Jacobian is moot: resolve
    takes the method's own, says why, and trains no field; it does not refuse at run time."""
    import services.solver.optimize.rules.fields as fields
    from services.solver.optimize.resolve import resolve

    def effects(facts, method, uses, overrides, delta_depth):
        on, off = EffectChoice(True, ""), EffectChoice(False, "none of 512 probe rays reaches another surface")
        return Effects(on, on, on, off, EffectChoice(0, ""),
                       [ScalarEffect(f"s{i}", True, (0, 1, 2), "", 0) for i in range(6)])

    monkeypatch.setattr(fields, "choose_effects", effects)
    measures = SimpleNamespace(facts=lambda: None, closure=lambda: 0.1, direct=lambda: [True] * 6,
                               film=lambda: (64, 64), missing_energy=lambda depth: 0.0)
    parameters = SimpleNamespace(has_textures=False, has_geometry=False, n=6, sizes=[3, 3])
    recipe = resolve(_albedo_job(jacobian="differential-field", optimizer="levenberg-marquardt"), parameters, 8,
                     measures)
    assert (recipe.method, recipe.jacobian, recipe.fields_for, recipe.first_hits) == ("prb", "method", None, "fresh")
    assert not recipe.hybrid and not (recipe.radiance or recipe.differential)
    said = {d.what: d.reason for d in recipe.decisions}
    assert "none of 512 probe rays" in said["jacobian"] and "method's own Jacobian" in said["jacobian"]

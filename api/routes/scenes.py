"""``/v1/scenes``: the built-in scenes and the differentiable parameters of a scene."""

from __future__ import annotations

import asyncio
import tempfile
from pathlib import Path

from fastapi import APIRouter
from pydantic import BaseModel, Field

from api.deps import Authenticated, RuntimeDep
from api.problems import Problem, ProblemError
from api.routes.jobs import _preflight_lock
from schemas.job import XmlScene

router = APIRouter(prefix="/v1/scenes", tags=["scenes"], dependencies=[Authenticated],
                   responses={401: {"model": Problem}})


class SceneSummary(BaseModel):
    name: str = Field(description="Built-in scene name.")
    description: str = Field(description="What the scene shows.")


class ParameterPublic(BaseModel):
    key: str = Field(description="mi.traverse key, as used in a job's parameters.")
    size: int = Field(description="Number of scalars (an RGB value counts 3).")
    owner: str = Field(description="'bsdf' or 'emitter'.")
    owner_type: str = Field(description="Mitsuba plugin class, e.g. SmoothDiffuse, AreaLight.")
    value: list[float] = Field(description="Current value in the scene.")


class SceneParameters(BaseModel):
    parameters: list[ParameterPublic] = Field(description="Optimizable parameters, in traversal order.")
    sensors: list[list[int]] = Field(description="[width, height] of every sensor's film.")


@router.get("", response_model=list[SceneSummary], summary="Built-in scenes")
def list_scenes():
    from services.scene.builtin import BUILTIN_SCENES

    return [SceneSummary(name=name, description=text) for name, (_, text) in BUILTIN_SCENES.items()]


def _describe(**source) -> SceneParameters:
    from services.scene.load import load_scene
    from services.scene.params import differentiable_parameters

    with _preflight_lock, tempfile.TemporaryDirectory(prefix="ndrf-scene-") as tmp:
        scene = load_scene(folder=Path(tmp) if "xml" in source else None, **source)
        params = [ParameterPublic(key=p.key, size=p.size, owner=p.owner, owner_type=p.owner_type, value=list(p.value))
                  for p in differentiable_parameters(scene.params)]
        sensors = [list(scene.resolution(i)) for i in range(scene.sensor_count)]
    return SceneParameters(parameters=params, sensors=sensors)


@router.get("/{name}/parameters", response_model=SceneParameters, responses={404: {"model": Problem}},
            summary="Parameters of a built-in scene")
async def builtin_parameters(name: str):
    from services.scene.builtin import BUILTIN_SCENES

    if name not in BUILTIN_SCENES:
        raise ProblemError(404, "Not found", f"no built-in scene {name!r}; known: {', '.join(BUILTIN_SCENES)}",
                           slug="unknown-scene")
    return await asyncio.to_thread(_describe, builtin=name)


@router.post("/parameters", response_model=SceneParameters, responses={422: {"model": Problem}},
             summary="Parameters of an uploaded scene")
async def uploaded_parameters(scene: XmlScene, runtime: RuntimeDep):
    """The same sandbox as job submission applies (only the uploaded files can be read)."""
    from services.scene.sandbox import SandboxError, UploadLimits, check_scene_upload

    limits = runtime.settings.limits
    try:
        files = check_scene_upload(scene.xml, scene.files,
                                   UploadLimits(max_file_bytes=limits.mesh_bytes, max_total_bytes=limits.upload_bytes))
    except SandboxError as exc:
        raise ProblemError(422, "Invalid scene", str(exc), slug="invalid-scene", errors=[(exc.field, exc.message)]) from None
    try:
        return await asyncio.to_thread(_describe, xml=scene.xml, files=files)
    except (RuntimeError, ValueError, FileNotFoundError) as exc:
        raise ProblemError(422, "Invalid scene", f"Mitsuba could not load the scene: {exc}", slug="invalid-scene",
                           errors=[("scene.xml", str(exc))]) from None

"""``/v1/scenes``: the built-in scenes and the differentiable parameters of a scene (loaded in a
sandboxed child process, like a job's)."""

from __future__ import annotations

from fastapi import APIRouter, Depends
from pydantic import BaseModel, Field

from api.bodies import GuardedRoute
from api.deps import CallerDep, RuntimeDep, require_caller
from api.problems import ProblemDetails, ProblemError
from schemas.errors import InvalidJob
from schemas.job import BuiltinScene, SceneSpec, XmlScene
from schemas.scenes import BUILTIN_SCENES
from services.jobs.preflight import describe_scene
from services.runtime import Runtime

router = APIRouter(route_class=GuardedRoute, prefix="/v1/scenes", tags=["scenes"], dependencies=[Depends(require_caller)],
                   responses={401: {"model": ProblemDetails}})


class SceneSummary(BaseModel):
    name: str = Field(description="Built-in scene name.")
    description: str = Field(description="What the scene shows.")


class ParameterPublic(BaseModel):
    key: str = Field(description="mi.traverse key, as used in a job's parameters.")
    size: int = Field(description="Number of scalars (an RGB value counts 3).")
    owner: str = Field(description="'bsdf' or 'emitter'.")
    owner_type: str = Field(description="Mitsuba plugin class, e.g. SmoothDiffuse, AreaLight.")
    value: list[float] = Field(description="Current value in the scene (a texture: its mean per channel).")
    shape: list[int] | None = Field(None, description="[H, W, C] of a texture parameter (a bitmap's data, "
                                                      "recovered texel by texel); null for a value.")


class SceneParameters(BaseModel):
    parameters: list[ParameterPublic] = Field(description="Optimizable parameters, in traversal order.")
    sensors: list[list[int]] = Field(description="[width, height] of every sensor's film.")


@router.get("", response_model=list[SceneSummary], summary="Built-in scenes")
def list_scenes():
    return [SceneSummary(name=name, description=text) for name, text in BUILTIN_SCENES.items()]


async def _describe(scene: SceneSpec, runtime: Runtime, owner: str) -> SceneParameters:
    try:
        found = await runtime.admission.run(owner, describe_scene, scene, runtime.settings.limits)
    except InvalidJob as exc:
        raise ProblemError(422, "Invalid scene", str(exc), slug="invalid-scene", errors=[(exc.field, exc.message)]) from None
    return SceneParameters.model_validate(found)


@router.get("/{name}/parameters", response_model=SceneParameters, responses={404: {"model": ProblemDetails}},
            summary="Parameters of a built-in scene")
async def builtin_parameters(name: str, runtime: RuntimeDep, caller: CallerDep):
    if name not in BUILTIN_SCENES:
        raise ProblemError(404, "Not found", f"no built-in scene {name!r}; known: {', '.join(BUILTIN_SCENES)}",
                           slug="unknown-scene")
    return await _describe(BuiltinScene(builtin=name), runtime, caller.owner)


@router.post("/parameters", response_model=SceneParameters, responses={422: {"model": ProblemDetails}},
             summary="Parameters of an uploaded scene")
async def uploaded_parameters(scene: XmlScene, runtime: RuntimeDep, caller: CallerDep):
    """The same upload checks as job submission apply (only the uploaded files can be read)."""
    return await _describe(scene, runtime, caller.owner)

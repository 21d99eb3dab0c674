"""``plan.json``: what a run simulates and why, written when it starts and at every event (a
larger batch, a remesh, the stop). The names are those of the glossary (``docs/method/index.md``):
``target_values`` as in ``summary.json``, ``events`` as the run's decisions.

A plan of an older version may lack fields (they read as None) or hold ones since dropped (kept
as they were, so an old job folder is served unchanged).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field


class Plan(BaseModel):
    """What a run simulates and why (module docstring)."""

    model_config = ConfigDict(extra="allow")   # an older version's fields, kept as written

    method: str | None = Field(None, description="The gradient method that runs (an auto job's choice).")
    device: dict[str, Any] | None = Field(None, description="Where the run computes: the Dr.Jit variant and the "
                                          "torch device.")
    recipe: dict[str, Any] | None = Field(None, description="The job resolved once: every setting with the "
                                          "decision and reason that set it (docs/method/recipe.md).")
    events: list[dict[str, Any]] = Field(default_factory=list, description="Decisions taken on the way (a larger "
                                         "batch, a remesh, the stop), each with its iteration and reason.")
    realised_by: str | None = Field(None, description="The class that computes the method's gradient.")
    fields: dict[str, bool] | None = Field(None, description="Which neural fields the run trains: radiance "
                                           "(L_phi) and differential (dL_theta).")
    scalars: list[str] | None = Field(None, description="Label of each listed scalar (textures are summarised).")
    keys: list[str] | None = Field(None, description="The scene parameters optimized, in order.")
    init: list[float] | None = Field(None, description="Initial value of each listed scalar.")
    lower: list[float | None] | None = Field(None, description="Lower bound of each listed scalar (None: none).")
    upper: list[float | None] | None = Field(None, description="Upper bound of each listed scalar (None: none).")
    target_values: list[float] | None = Field(None, description="Target value of each listed scalar (synthetic "
                                              "targets only).")
    textures: list[dict[str, Any]] | None = Field(None, description="Each texture parameter: its key, size and "
                                                  "the summaries of its initial and target values.")
    shapes: dict[str, dict[str, Any]] | None = Field(None, description="Each optimized mesh at the start, by shape "
                                                     "id, with its LargeSteps lambda.")
    sensors: list[int] | None = Field(None, description="The target views (sensor indices).")
    resolution: list[int] | None = Field(None, description="Film [width, height].")
    depths: dict[str, Any] | None = Field(None, description="Path depth of the renders and of the targets, and the "
                                          "warnings about bias.")
    prepared_seconds: dict[str, float] | None = Field(None, description="Seconds of the set-up: load, targets, "
                                                      "resolve.")
    render: dict[str, Any] | None = Field(None, description="The job's render settings.")
    training: dict[str, Any] | None = Field(None, description="The job's training settings of the fields.")
    effects: dict[str, Any] | None = Field(None, description="The light transport the run simulates, and why "
                                           "(docs/method/effects.md).")
    iterations: int | None = Field(None, description="The cap of iterations.")
    warm_start: dict[str, Any] | None = Field(None, description="What a warm start took from its source job.")

"""``summary.json``: how a finished run ended and its answer, one name per idea (the glossary of
``docs/method/index.md``). The answer is ``estimate``, as in every iteration's record
(:class:`~schemas.records.IterationRecord`); how it was formed is ``estimate_kind`` and
``estimate_window``; the truth of a synthetic job is ``target_values``, as in ``plan.json``.

A job folder written before these names (``final``, ``target``, ``max_abs_error``, and
``estimate`` holding how the answer was formed) is read into the same model (:meth:`Summary.read`).
"""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, ConfigDict, Field, model_validator


class Summary(BaseModel):
    """How a run ended (module docstring)."""

    model_config = ConfigDict(extra="forbid")

    status: str = Field(description="succeeded, failed, canceled (interrupted: the run stopped to resume later).")
    method: str | None = Field(None, description="The gradient method that ran (an auto job's choice).")
    iterations: int = Field(ge=0, description="Iterations completed.")
    seconds: float = Field(ge=0.0, description="Seconds the run took, from preparing to its end.")
    scalars: list[str] | None = Field(None, description="Label of each listed scalar (textures are summarised).")
    init: list[float] | None = Field(None, description="Initial value of each listed scalar.")
    estimate: list[float] | None = Field(None, description="The answer: the best estimate of each listed scalar "
                                         "from the iterations of its window, not the last iterate.")
    standard_error: list[float] | None = Field(None, description="Standard error of each scalar of estimate (None: "
                                               "too few iterations to tell, or no window of them that "
                                               "a test showed settled: the run was still moving).")
    estimate_kind: str | None = Field(None, description="How the estimate was formed: the window's mean, or the "
                                      "Newton point of the quadratic model it fits.")
    estimate_window: list[int] | None = Field(None, description="[first, last] iteration the estimate averages.")
    run_error: list[float] | None = Field(None, description="The part of standard_error from the iterates' spread.")
    floor_error: list[float] | None = Field(None, description="The part of standard_error that the targets' noise "
                                            "and the model's misfit leave, which no iteration removes.")
    last_iterate: list[float] | None = Field(None, description="The parameters of the last step, not averaged.")
    stopped: dict[str, Any] | None = Field(None, description="Why the run stopped: the stop event, with its reason.")
    target_values: list[float] | None = Field(None, description="Target value of each scalar (synthetic targets).")
    estimate_error: float | None = Field(None, description="max |estimate - target_values| (synthetic targets).")
    error: str | None = Field(None, description="Why the job failed.")
    field: str | None = Field(None, description="The job-file field an error concerns.")
    textures: dict[str, dict[str, str]] | None = Field(None, description="Each recovered texture's files under "
                                                       "final/, by texture key.")
    poses: list[dict[str, Any]] | None = Field(None, description="Each posed shape's answer: its 4x4 matrix and "
                                               "the XML <transform> to paste back (final/poses.json).")
    meshes: dict[str, dict[str, Any]] | None = Field(None, description="Each optimized mesh's answer, by shape id: "
                                                     "its file under final/, vertices, faces, Chamfer distance.")

    @model_validator(mode="before")
    @classmethod
    def _older_names(cls, data: Any) -> Any:
        """An older job folder's names: ``final`` (the answer), ``estimate`` (how it was formed),
        ``target``, ``max_abs_error``."""
        if not isinstance(data, dict) or "final" not in data:
            return data
        data = dict(data)
        formed = data.pop("estimate", None) or {}
        data["estimate"] = data.pop("final")
        data.setdefault("estimate_kind", formed.get("kind"))
        data.setdefault("estimate_window", formed.get("window"))
        data.setdefault("run_error", formed.get("run_error"))
        data.setdefault("floor_error", formed.get("floor_error"))
        if "target" in data:
            data["target_values"] = data.pop("target")
        if "max_abs_error" in data:
            data["estimate_error"] = data.pop("max_abs_error")
        return data

    @classmethod
    def read(cls, data: str | bytes | dict) -> Summary:
        """A ``summary.json`` of this or an older version (its text, or the dict it parses to)."""
        return cls.model_validate(data) if isinstance(data, dict) else cls.model_validate_json(data)

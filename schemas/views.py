"""A view of a job's fields (``POST /v1/jobs/{id}/views``, ``ndrf view JOB_DIR``): the camera to
render ``L_phi`` and every scalar's ``dL_theta`` from, at the first hits of its rays (paper Sec.
7.1, Fig. 4b), and optionally ``prb``'s gradient image from the same camera to compare with.

The camera is either free (``origin``, ``target``, ``up``, ``fov``) or one of the scene's sensors
(``sensor``) translated by ``offset``; never both.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field, model_validator

Vector3 = tuple[float, float, float]

#: The largest film side of a view, in pixels.
MAX_VIEW_SIDE = 512
#: The most first-hit samples per pixel of a view.
MAX_VIEW_SPP = 64
#: The most samples per pixel of the ``prb`` comparison image.
MAX_PRB_SPP = 4096


class ViewRequest(BaseModel):
    """One view of a job's fields."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    origin: Vector3 | None = Field(default=None, description="Camera position (world units); with target, up, fov.")
    target: Vector3 | None = Field(default=None, description="The point the camera looks at.")
    up: Vector3 = Field(default=(0.0, 1.0, 0.0), description="The camera's up direction.")
    fov: float = Field(default=40.0, gt=0.0, lt=180.0, description="Horizontal field of view, degrees.")
    sensor: int | None = Field(default=None, ge=0, le=64,
                               description="Instead of origin/target: this scene sensor, moved by offset.")
    offset: Vector3 = Field(default=(0.0, 0.0, 0.0),
                            description="Translation of the sensor's camera (world units); with sensor only.")
    resolution: tuple[int, int] | None = Field(
        default=None, description=f"Film width and height, 8 to {MAX_VIEW_SIDE} pixels each (default: the job's "
                                  f"render.resolution, or the sensor's film).")
    spp: int = Field(default=4, ge=1, le=MAX_VIEW_SPP,
                     description="Fixed first-hit samples per pixel (the fields are queried at each).")
    prb_spp: int | None = Field(default=None, ge=1, le=MAX_PRB_SPP,
                                description="Also render prb's gradient image from the same camera at this spp "
                                            "(forward mode, one render per group of scalars; slow).")
    seed: int = Field(default=0, ge=0, le=2**31 - 1, description="Seed of the pixel samples.")
    inline: bool = Field(default=False,
                         description="Answer the PNGs in the response (images: name -> data URL) and store "
                                     "nothing (no files, no disk budget): for interactive viewers such as the "
                                     "dashboard's orbit viewer.")

    @model_validator(mode="after")
    def _one_camera(self) -> ViewRequest:
        free = self.origin is not None or self.target is not None
        if free and self.sensor is not None:
            raise ValueError("give either origin/target (a free camera) or sensor (with offset), not both")
        if not free and self.sensor is None:
            raise ValueError("give origin and target (a free camera) or sensor (with offset)")
        if free and (self.origin is None or self.target is None):
            raise ValueError("a free camera needs both origin and target")
        if self.sensor is None and any(self.offset):
            raise ValueError("offset moves a scene sensor: give sensor too")
        if self.resolution is not None and not all(8 <= side <= MAX_VIEW_SIDE for side in self.resolution):
            raise ValueError(f"resolution {list(self.resolution)}: each side must be within [8, {MAX_VIEW_SIDE}]")
        return self


class ViewFiles(BaseModel):
    """What a view wrote (``POST /v1/jobs/{id}/views``): each file by name with its URL."""

    id: str = Field(description="The view's id (its files are under views/<id>/ of the job).")
    files: dict[str, str] = Field(description="File name -> URL: radiance.npy/.png, gradients.npy, "
                                              "gradient-<p>.png per scalar, prb.npy and prb-<p>.png when asked, "
                                              "view.json.")
    scalars: list[str] = Field(description="The scalars of gradients.npy's first axis.")
    seconds: dict[str, float] = Field(description="Seconds spent: load (scene, fields), fields (the view), prb.")
    iteration: int | None = Field(default=None, description="The checkpoint's next iteration (its fields' age).")
    images: dict[str, str] = Field(default_factory=dict,
                                   description="With inline: radiance.png, gradient-<p>.png (and prb-<p>.png) as "
                                               "data:image/png;base64 URLs; files is then empty.")
    camera: dict = Field(default_factory=dict, description="The camera rendered: origin, target, up, fov and "
                                                           "resolution (a sensor's too: its target is the point "
                                                           "of its axis nearest the scene's centre).")
    warm: bool = Field(default=False, description="Whether a warm view child of this job's checkpoint answered "
                                                  "(no child start, scene load or checkpoint restore).")

"""The inverse-rendering job file (``ndrf run JOB.json``, ``POST /v1/jobs``).

A job names a scene, the parameters to recover with their initial values and bounds, the target
images (rendered from known values, or uploaded), a gradient method and the budget. Everything
but ``scene``, ``parameters`` and ``targets`` has a default. Unknown fields are errors, so a typo
is reported instead of silently ignored.
"""

from __future__ import annotations

import hashlib
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from schemas.methods import METHOD_HELP, OLDER_METHOD_NAMES, Method
from schemas.solver import TrainingConfig


class _Strict(BaseModel):
    """Unknown fields are errors, and so are NaN and Infinity in any number (JSON has neither;
    Python's parser accepts them, and a NaN would otherwise be stored as null)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


# ------------------------------------------------------------------------------------ scene

class BuiltinScene(_Strict):
    """A scene shipped with the service."""

    builtin: str = Field(description="Name of a built-in scene: cornell-box, hidden-object, mirror-box "
                                     "(GET /v1/scenes lists them).", min_length=1, max_length=64)


class XmlScene(_Strict):
    """A Mitsuba 3 XML scene and the files it names (includes, meshes, textures)."""

    xml: str = Field(description="The Mitsuba 3 XML document.", min_length=1)
    files: dict[str, str] = Field(default_factory=dict,
                                  description="Files the XML names, by path relative to it, as base64.")


class PathScene(_Strict):
    """A Mitsuba 3 XML file on the local disk (CLI only; the service refuses host paths)."""

    path: str = Field(description="Path of the XML file, relative to the job file.", min_length=1)


SceneSpec = BuiltinScene | XmlScene | PathScene


# ------------------------------------------------------------------------------- parameters

Scalars = float | list[float]


class ParameterSpec(_Strict):
    """One scene parameter to recover (a ``mi.traverse`` key). A bitmap texture's ``data`` (e.g.
    ``wall.reflectance.data``) is a texture parameter: all its texels are recovered (prb, direct,
    radiance-cache, or ndrf-rhs with training.head)."""

    key: str = Field(description="Mitsuba traverse key, e.g. 'red.reflectance.value', or a bitmap texture's "
                                 "data, e.g. 'wall.reflectance.data' (a texture parameter).",
                     min_length=1, max_length=256)
    init: Scalars | None = Field(None, description="Initial value (a number, or one per component; a single "
                                                   "number is broadcast; for a texture also one per channel, "
                                                   "repeated at every texel). Default: the scene's own value "
                                                   "(for a texture: the scene file's texture).")
    bounds: tuple[float, float] | None = Field(
        None, description="[lower, upper] projection bounds after each step (per texel for a texture). Default: "
                          "[0, 1] for BSDF parameters, [0, +inf) for emitters.")

    @field_validator("bounds")
    @classmethod
    def _ordered(cls, bounds):
        if bounds is not None and not bounds[0] <= bounds[1]:
            raise ValueError(f"bounds must be [lower, upper] with lower <= upper, got {list(bounds)}")
        return bounds


# ---------------------------------------------------------------------------------- targets

class TargetMesh(_Strict):
    """A shape job's synthetic target shape, of any topology: the shape's own mesh (default), a
    mesh ``file`` or a ``builtin`` one, deformed (``scale``, ``bump``) about the centre of its own
    bounding box. The records' Chamfer distance compares surfaces, whatever their vertices."""

    file: str | None = Field(None, min_length=1, max_length=1024,
                             description="A PLY or OBJ file that is the target shape, its vertices in the scene's "
                                         "world space (as the shape's vertex_positions are): a path among an "
                                         "uploaded XML scene's files, or relative to a local XML scene's folder "
                                         "(ndrf run). Not with a built-in scene, nor with builtin. Default: the "
                                         "shape's own mesh.")
    builtin: Literal["rounded-box"] | None = Field(
        None, description="A target mesh the project generates: 'rounded-box', a rounded cube on its own grid (866 "
                          "vertices) centred on the centre of the shape's bounding box, its corners at the shape's "
                          "radius. Not with file. Default: the shape's own mesh.")
    scale: tuple[float, float, float] = Field((1.0, 1.0, 1.0), description="Scaling per axis (x, y, z), applied "
                                                                          "after the bump; each in [0.1, 10].")
    bump: float = Field(0.0, ge=-1.0, le=1.0, description="Height of a smooth radial bump, in radii of the shape "
                                                          "(its farthest vertex from the centre); 0: none.")
    bump_direction: tuple[float, float, float] = Field((0.0, 1.0, 0.0), description="Where the bump points from "
                                                                                    "the centre (any length).")
    bump_width: float = Field(0.5, ge=0.05, le=3.0, description="Angular width of the bump in radians: a vertex at "
                                                                "angle a from its direction moves out by "
                                                                "bump x radius x exp(-(a / width)^2).")

    @field_validator("scale")
    @classmethod
    def _scale(cls, scale):
        if not all(0.1 <= s <= 10.0 for s in scale):
            raise ValueError(f"scale must lie in [0.1, 10] per axis, got {list(scale)}")
        return scale

    @model_validator(mode="after")
    def _one_source(self):
        if self.file is not None and self.builtin is not None:
            raise ValueError(f"a target mesh is a file or a builtin mesh, not both (got file {self.file!r} and "
                             f"builtin {self.builtin!r})")
        return self


class SyntheticTarget(_Strict):
    """Render the target from the same scene with known parameter values."""

    values: dict[str, Scalars | None] = Field(
        description="Parameter values of the target, by key (as a parameter's init); null: the scene's own value "
                    "(for a texture, the scene file's texture: the usual synthetic texture target). A shape "
                    "parameter (<shape id>.vertex_positions) takes its target from meshes instead.")
    meshes: dict[str, TargetMesh] = Field(
        default_factory=dict, max_length=16,
        description="Target shapes of shape parameters, by shape id (TargetMesh): the shape's own mesh, a mesh file "
                    "or a builtin mesh, deformed; the target is rendered with it in the shape's place, and the "
                    "records report the Chamfer distance to it.")
    spp: int = Field(256, ge=1, le=65536, description="Samples per pixel of the target rendering.")
    max_depth: int | None = Field(
        None, ge=1, le=1024, description="Path depth of the target rendering. Default: unbounded, paths ended "
                                         "by Russian roulette from depth rr_depth (unbiased: the target has every "
                                         "bounce, as a photograph has).")
    rr_depth: int = Field(5, ge=1, le=1024, description="Depth from which Russian roulette ends target paths "
                                                        "(Mitsuba's default; unbiased).")


class ImageTarget(_Strict):
    """An uploaded target photograph for one sensor."""

    sensor: int = Field(0, ge=0, le=64, description="Index of the scene sensor this image was taken with.")
    data: str = Field(description="Base64 of an EXR, PNG or NPY image (linear RGB; PNG is sRGB-decoded).",
                      min_length=1)


class SyntheticTargets(_Strict):
    synthetic: SyntheticTarget = Field(description="A target rendered from known values.")


class ImageTargets(_Strict):
    images: list[ImageTarget] = Field(description="Target images; several sensors make a multi-view job "
                                                  "(losses are summed).", min_length=1, max_length=64)


TargetSpec = SyntheticTargets | ImageTargets


# ----------------------------------------------------------------------------------- render

class RenderSpec(_Strict):
    """How candidate images and gradients are rendered."""

    spp: int = Field(1, ge=1, le=4096, description="Samples per pixel of the candidate render (Sec. 5, step 2). "
                                                   "1 is fastest to a given error in every scene measured (bench/): "
                                                   "the optimizer averages the noise across iterations.")
    gradient_spp: int = Field(1, ge=1, le=4096,
                              description="Samples per pixel of the gradient query (camera rays for ndrf-*, "
                                          "radiance-cache and direct; paths for prb) and of the Jacobian.")
    resolution: tuple[int, int] | None = Field(None, description="[width, height] overriding the scene's film.")
    max_depth: int | None = Field(
        None, ge=1, le=1024, description="Path depth of the path-traced candidate, of prb and of its Jacobian. "
                                         "Default: unbounded, paths ended by Russian roulette from rr_depth, as "
                                         "Mitsuba does: unbiased, so the candidate has every bounce a photograph "
                                         "has. A finite depth truncates light paths (biased in bright closed "
                                         "rooms: the plan warns).")
    rr_depth: int | None = Field(
        5, ge=1, le=1024, description="Depth from which Russian roulette ends paths (Mitsuba's default 5). Roulette "
                                      "is unbiased: it re-weights the paths it keeps. Null turns it off; max_depth "
                                      "must then be set.")
    candidate: Literal["path", "field"] = Field(
        "path", description="How the candidate image is formed (Sec. 5, step 2): 'path' path-traces it with spp "
                            "samples and render.max_depth bounces; 'field' evaluates emission + L_phi at the camera's "
                            "first hits, cached once per job at gradient_spp fixed samples per pixel: no path "
                            "tracing, every bounce (L_phi holds them), biased by the field's error.")
    first_hits: Literal["fresh", "cached"] = Field(
        "fresh", description="'cached': trace the camera rays' first hits once per job at gradient_spp fixed "
                             "samples per pixel (geometry is fixed) and let ndrf-lhs query dL_theta there every "
                             "iteration, contracting dz/dy per ray; 'fresh': new camera samples every iteration.")

    freeze: bool = Field(
        True, description="Replay prb's differentiable render from recorded kernels (Dr.Jit's dr.freeze): the first "
                          "iteration of each view records the render, its loss and its adjoint pass, later ones run "
                          "them with the new parameters and seed without tracing them again in Python (about a third "
                          "of a 1-spp iteration on a CPU; bench.prb_iteration). False traces every iteration, as "
                          "Mitsuba's tutorial loop does.")

    @field_validator("resolution")
    @classmethod
    def _positive(cls, resolution):
        if resolution is not None and not (1 <= resolution[0] <= 8192 and 1 <= resolution[1] <= 8192):
            raise ValueError(f"resolution must be [width, height] within 1..8192, got {list(resolution)}")
        return resolution

    @model_validator(mode="after")
    def _terminates(self):
        if self.max_depth is None and self.rr_depth is None:
            raise ValueError("render.rr_depth null (no Russian roulette) needs a finite render.max_depth")
        return self


# ---------------------------------------------------------------------------------- effects

Switch = Literal["auto", "on", "off"]


class EffectOverrides(_Strict):
    """Override `choose_effects`, which otherwise simulates only what the scene and the chosen
    parameters can produce (the plan, with a reason per decision, is part of the job's record).
    Forcing off an effect the plan needs biases the gradients; the plan says so in a warning."""

    emission_term: Switch = Field("auto", description="∂E: derivative of emission (non-zero for emitter parameters).")
    bsdf_term: Switch = Field("auto", description="(∂f) L: derivative of the BSDFs (non-zero for BSDF parameters).")
    radiance_field: Switch = Field("auto", description="Train L_phi (needed for BSDF parameters under interreflection).")
    differential_field: Switch = Field("auto", description="Train dL_theta (needed when light bounces between surfaces).")
    delta_depth: int | None = Field(None, ge=0, le=64, description="Ideal-specular bounces to follow (default: what "
                                                                   "the scene needs, at most training.delta_depth).")
    drop_unreachable: bool = Field(True, description="Give scalars that cannot change the image a zero gradient "
                                                     "without training for them.")
    merge_channels: bool = Field(True, description="Carry only the RGB channels a scalar can change in dL_theta "
                                                   "(an RGB albedo component changes one channel).")


# --------------------------------------------------------------------------------- geometry

#: The remeshing schedule's fields: at their defaults they hash as before they existed.
REMESH_FIELDS = {"remesh_at", "remesh_edge", "remesh_passes"}

class GeometrySettings(_Strict):
    """How geometry parameters (a pose, ``<shape id>.vertex_positions``) are optimized (ignored by
    jobs without one; ``services.solver.scene.shape``, ``services.solver.optimize.blur``)."""

    blur_px: Annotated[float, Field(ge=0.0, le=64.0)] | Literal["auto"] = Field(
        "auto", description="Coarse to fine: the standard deviation, in pixels, of the Gaussian that blurs both the "
                            "render and the target in the loss at the first iteration. A pose far from its target "
                            "overlaps it only once both are blurred, and only then does the loss's downhill direction "
                            "point towards it. auto: a sixteenth of the film's smaller side for a pose, 0 (off) for "
                            "vertex positions; 0: off.")
    blur_end_px: float = Field(1.0, ge=0.0, le=64.0, description="The blur's standard deviation, in pixels, once it "
                                                                 "has narrowed (kept to the end of the run).")
    blur_share: float = Field(0.4, gt=0.0, le=1.0, description="The share of the iterations over which the blur "
                                                               "narrows linearly from blur_px to blur_end_px.")

    largesteps_lambda: float = Field(
        19.0, ge=0.0, le=1e4, description="λ of the LargeSteps parameterization (Nicolet et al. 2021, Mitsuba's "
                                          "mi.ad.LargeSteps): the optimizer steps u = (I + λ L) v, L the mesh's "
                                          "Laplacian, and the vertices are v = (I + λ L)^-1 u, so a gradient on a few "
                                          "silhouette vertices moves their neighbourhood smoothly. Larger: smoother "
                                          "steps (raise it with the mesh's resolution); 0: the vertices themselves.")
    remesh_at: list[Annotated[int, Field(ge=1, le=100000)]] = Field(
        default_factory=list, max_length=16,
        description="Iterations before which every optimized mesh is remeshed (Botsch-Kobbelt isotropic remeshing, as "
                    "Mitsuba's shape tutorial does between its two stages): the mesh of the run's estimate is remeshed "
                    "to edges of remesh_edge times its mean edge length, its LargeSteps operator is rebuilt on the new "
                    "triangles, and the optimizer, its learning-rate decay and the answer start again from there. "
                    "Each in [1, iterations - 1]; a job with a shape parameter only. Empty: the triangles stay as "
                    "loaded.")
    remesh_edge: float = Field(0.5, ge=0.25, le=4.0, description="The remeshed edge length, as a multiple of the mesh's "
                                                                 "mean edge length at the remesh (0.5, the tutorial's: "
                                                                 "edges halved, about four times the vertices).")
    remesh_passes: int = Field(5, ge=1, le=20, description="Passes of split, collapse, flip and relaxation of the "
                                                            "remeshing (the tutorial's 5).")

    @field_validator("remesh_at")
    @classmethod
    def _remesh_sorted(cls, at):
        if list(at) != sorted(set(at)):
            raise ValueError(f"remesh_at must be increasing iterations without repeats, got {list(at)}")
        return at


# --------------------------------------------------------------------------------- textures

class TextureSettings(_Strict):
    """How texture parameters are optimized (ignored by jobs without one;
    ``services.solver.optimize.regularize``). Each setting's effect is measured in
    ``bench/results/textures.md``."""

    smoothness: Literal["none", "laplacian", "tv"] = Field(
        "none", description="A smoothness penalty on differences between neighbouring texels, added to the step's "
                            "gradient (the reported loss stays the image loss): 'laplacian' (squared differences) "
                            "or 'tv' (total variation, keeps edges).")
    smoothness_weight: float = Field(1.0, ge=0.0, le=1e6, description="Weight of the smoothness penalty, which is "
                                                                      "averaged over neighbour pairs (independent "
                                                                      "of the texture's size).")
    resolution: Literal["auto", "full"] = Field(
        "auto", description="The resolution a texture is optimized at. 'auto': its own, unless the pixels that see it "
                            "directly (its footprint, measured before the first iteration) cannot pin its texels "
                            "down, fewer than 4 pixels per texel: then blocks of 2x2, 4x4, ... texels move together "
                            "(each block's gradient averaged), the smallest blocks that 4 pixels each see; plan.json "
                            "gives the footprint and the choice. 'full': always its own resolution.")
    coarse_to_fine: int = Field(0, ge=0, le=8, description="Levels of a coarse-to-fine schedule: the first half of "
                                                           "the iterations is split into this many stages that "
                                                           "optimize the texture at 1/2^L, ..., 1/2 of its "
                                                           "resolution (the gradient averaged over blocks); 0: "
                                                           "full resolution throughout.")


# ------------------------------------------------------------------------------------- stop

class StopSettings(_Strict):
    """When a run ends before ``iterations``, which stays the cap. The answer a run returns is
    the estimate of its window with a standard error per scalar (``summary.json``); these settings
    end the run once that answer is good enough, and ``plan.json``'s events say why it stopped."""

    standard_error: float | None = Field(
        None, gt=0, le=1e6, description="Stop once the standard error of every listed scalar is at most this (in "
                                        "the scalar's own units; with relative, as a fraction of the scalar's "
                                        "estimate). Null: no accuracy requested.")
    relative: bool = Field(False, description="standard_error is relative: a scalar's standard error is compared "
                                              "with standard_error x max(|estimate|, 0.01).")
    auto: bool = Field(True, description="Stop by itself when more iterations would not improve the answer: once "
                                         "the run's own Monte Carlo noise is under half of what the targets' noise "
                                         "and the model's misfit leave in every scalar, and has been at each of "
                                         "the last quarter of the run's iterations (doubling the run would then "
                                         "lower the standard error by less than 6%). Needs the curvature of "
                                         "second-order steps; a first-order run stops at iterations.")


# -------------------------------------------------------------------------------------- job

#: The optimizers that step from a Jacobian (``services.solver.optimize.optimizers``).
SECOND_ORDER = ("levenberg-marquardt", "gauss-newton")

class WarmStart(_Strict):
    """Start from another job's trained fields (and optionally its parameters)."""

    job: str = Field(pattern=r"^[A-Za-z0-9][A-Za-z0-9._-]{0,99}$",
                     description="Id of a job of the same API key with the same scene and parameter keys (with ndrf "
                                 "run: the name of a job folder beside --out); its latest checkpoint is used.")
    parameters: bool = Field(False, description="Also start from that job's parameters (else each parameter's init).")
    top_up_steps: int | None = Field(None, ge=0, le=100000,
                                     description="Most training steps of the adaptive top-up that replaces the "
                                                 "warm-up (it stops when the residuals plateau). Default: a quarter "
                                                 "of training.warmup_steps.")


class JobSpec(_Strict):
    """An inverse-rendering job (paper Sec. 5)."""

    name: str | None = Field(None, max_length=200, description="Optional label.")
    scene: SceneSpec = Field(description="The scene: {'builtin': NAME} or {'xml': ..., 'files': {...}}.")
    parameters: list[ParameterSpec] = Field(min_length=1, max_length=64, description="Parameters to recover.")
    targets: TargetSpec = Field(description="{'synthetic': {...}} or {'images': [...]}.")
    method: Method | Literal["auto"] = Field("auto", description=METHOD_HELP)
    iterations: int = Field(60, ge=1, le=100000, description="Optimization iterations: parameter steps, each on "
                                                           "views_per_iteration of the target views.")
    views_per_iteration: int | Literal["auto"] = Field(
        "auto", description="Target views rendered per iteration (a mini-batch; the loss, dz/dp and the Jacobian "
                            "come from them, scaled to estimate the loss summed over every view). 'auto': one view, "
                            "the batch doubled whenever the optimizer's steps turn noise-dominated (they keep "
                            "reversing): views up to every view, then samples per pixel, up to 16 times the first "
                            "batch. Views are drawn without replacement from a seeded permutation per pass over "
                            "the views, so a resumed run draws the same batches.")
    learning_rate: float = Field(0.05, gt=0, le=100.0,
                                 description="Step size of the scene parameters: Adam's learning rate, and the "
                                             "smallest trust radius (largest change of a scalar per iteration) of "
                                             "the Gauss-Newton and Levenberg-Marquardt steps.")
    adam_betas: tuple[float, float] = Field(
        (0.8, 0.99), description="Adam's decay rates of the first and second moment estimates, each in [0, 1). "
                                  "Shorter than the usual (0.9, 0.999): with noisy Monte Carlo gradients and tens of "
                                  "iterations, a long first-moment memory overshoots the optimum and a long second-moment "
                                  "memory keeps the step large after the gradient has shrunk.")
    optimizer: Literal["auto", "adam", "levenberg-marquardt", "gauss-newton"] = Field(
        "auto", description="Update rule of the scene parameters (services/solver/optimize/optimizers/). 'adam': Adam "
                            "with adam_betas. 'levenberg-marquardt': damped Gauss-Newton steps from the Jacobian dy/dp "
                            "(H = (2/n) J^T J; l2 loss only) in a trust region that grows while consecutive steps "
                            "agree and halves when they reverse, never below the learning rate: for scalars that "
                            "trade against each other in the image (a curved valley, where Adam crawls) and for "
                            "reaching the answer in few steps. 'gauss-newton': the same steps with the trust radius "
                            "fixed at the learning rate. 'auto': Levenberg-Marquardt when the loss is l2 and the "
                            "Jacobian costs at most a few renders per view, else Adam (plan.json says why).")
    jacobian: Literal["method", "differential-field"] = Field(
        "method", description="Where the (Gauss-Newton, Levenberg-Marquardt) Jacobian dy/dp comes from. 'method': the "
                              "gradient method's own per-scalar images (prb: one forward-mode render per group of "
                              "scalars that change distinct RGB channels; ndrf-*: a field query). "
                              "'differential-field': dL_theta at the cached camera hits (Eq. 11), whatever the "
                              "gradient method: with prb, the hybrid of an unbiased gradient and NDRF's smooth "
                              "curvature (the fields are trained alongside).")
    jacobian_every: int = Field(1, ge=1, le=10000, description="Recompute the Jacobian every K iterations (the "
                                                               "curvature of the iterations between is reused).")
    damping: float = Field(1e-3, ge=0.0, le=1e6, description="Marquardt damping lambda of the Gauss-Newton and "
                                                             "Levenberg-Marquardt steps: they solve (H + lambda diag(H)) "
                                                             "delta = -grad. It must stay below the ratio of H's smallest "
                                                             "to largest curvature, or it damps exactly the valley "
                                                             "direction the step is for.")
    hessian: Literal["auto", "successive", "product", "cross"] = Field(
        "auto", description="Curvature from the Jacobian J. 'auto': 'cross' for a pose whose loss is blurred "
                            "(geometry.blur_px; its Jacobian changes as silhouettes move, so 'successive' would "
                            "mostly fall back to the biased product), else 'successive'. 'product': (2/n) J^T J "
                            "from one estimate, biased upwards by J's Monte Carlo variance, which damps the valley "
                            "direction (most where the signal is weak, as for an object seen only in reflections); "
                            "'cross': (1/n)(J_a^T J_b + J_b^T J_a) from two independent estimates, unbiased, one "
                            "more Jacobian per view; 'successive': the cross product of the view's Jacobian with its "
                            "previous one (independent samples, nearby parameters): unbiased where J changes slowly "
                            "and free; the product for a view's first Jacobian. Indefinite estimates have their "
                            "eigenvalues raised to 1e-6 of the largest.")
    final_learning_rate_ratio: float = Field(
        0.1, gt=0, le=1.0, description="Learning rate of the last iteration as a fraction of learning_rate "
                                       "(geometric decay; 1 keeps it constant). Noisy gradients need the decay "
                                       "to settle.")
    loss: Literal["l2", "l1"] = Field("l2", description="Image loss z(y): mean squared or mean absolute error.")
    render: RenderSpec = Field(default_factory=RenderSpec, description="Rendering settings.")
    training: TrainingConfig = Field(default_factory=TrainingConfig, description="Training of L_phi and dL_theta.")
    effects: EffectOverrides = Field(default_factory=EffectOverrides, description="Overrides of `choose_effects`.")
    textures: TextureSettings = Field(default_factory=TextureSettings,
                                      description="Regularization of texture parameters (a bitmap's data).")
    geometry: GeometrySettings = Field(default_factory=GeometrySettings,
                                       description="Optimization of shape parameters (a mesh's vertices).")
    stop: StopSettings = Field(default_factory=StopSettings,
                               description="When the run ends before iterations: at a requested standard error, or "
                                           "when more iterations would not improve the answer.")
    checkpoint_every: int = Field(10, ge=1, le=100000, description="Write a checkpoint every K iterations.")
    images_every: int | None = Field(
        None, ge=1, le=100000, description="Write the renders of every view and the gradient images every K "
                                           "iterations (records are written every iteration). Default: whenever "
                                           "the images written so far took less than images_budget of the run's "
                                           "time, and at the last iteration; the dashboard can ask for them at any "
                                           "iteration.")
    images_budget: float = Field(0.05, ge=0.0, le=1.0, description="Share of the run's time that images written on "
                                                                   "the default schedule may take.")
    seed: int = Field(0, ge=0, le=2**31 - 1, description="Seed of every random choice; equal seeds give equal runs.")
    warm_start: WarmStart | None = Field(
        None, description="Start from another job's L_phi and dL_theta (its latest checkpoint): the warm-up becomes a "
                          "short adaptive top-up. Refused unless the scene and the parameter keys match. plan.json's "
                          "warm_start says what was reused.")

    def fingerprint(self) -> str:
        """Hash of everything that changes the computation (not the name): a checkpoint is only
        loaded into the job it belongs to, and an Idempotency-Key only returns the same job. A job
        without ``warm_start``, with the default ``stop``, ``textures.resolution`` and ``geometry``
        (or its remeshing schedule) and no target meshes, hashes as before those fields existed, and so
        does a target mesh without ``file`` or ``builtin``; ``hessian: auto`` hashes as
        ``successive``, the default it replaced (what it resolves to for every job but a blurred pose)."""
        if self.hessian == "auto":
            return self.model_copy(update={"hessian": "successive"}).fingerprint()
        exclude: dict = {"name": True} if self.warm_start is not None else {"name": True, "warm_start": True}
        if self.stop == StopSettings():      # later fields, at their defaults, hash as before they existed
            exclude["stop"] = True
        if self.textures.resolution == "auto":
            exclude["textures"] = {"resolution"}
        if self.geometry == GeometrySettings():
            exclude["geometry"] = True
        elif self.geometry.model_dump(include=REMESH_FIELDS) == GeometrySettings().model_dump(include=REMESH_FIELDS):
            exclude["geometry"] = REMESH_FIELDS
        if isinstance(self.targets, SyntheticTargets):
            meshes = self.targets.synthetic.meshes
            later = {shape: {name for name in ("file", "builtin") if getattr(mesh, name) is None}
                     for shape, mesh in meshes.items()}
            exclude["targets"] = {"synthetic": {"meshes": {s: names for s, names in later.items() if names}}
                                  if meshes else {"meshes"}}
        return hashlib.sha256(self.model_dump_json(exclude=exclude).encode()).hexdigest()[:16]

    @field_validator("method", mode="before")
    @classmethod
    def _older_method_names(cls, value):
        """A job file or job folder of an older version names the projective methods with an
        underscore (``prb_projective``): read as today's name."""
        return OLDER_METHOD_NAMES.get(value, value) if isinstance(value, str) else value

    @field_validator("adam_betas")
    @classmethod
    def _betas(cls, betas):
        if not all(0.0 <= b < 1.0 for b in betas):
            raise ValueError(f"adam_betas must both lie in [0, 1), got {list(betas)}")
        return betas

    @model_validator(mode="after")
    def _consistent(self):
        keys = [p.key for p in self.parameters]
        if len(set(keys)) != len(keys):
            raise ValueError(f"parameter keys must be unique, got {keys}")
        if isinstance(self.targets, SyntheticTargets):
            meshes = self.targets.synthetic.meshes
            missing = [k for k in keys if k not in self.targets.synthetic.values
                       and not (k.endswith(".vertex_positions") and k[:-len(".vertex_positions")] in meshes)]
            if missing:
                raise ValueError(f"targets.synthetic.values has no value for {missing}")
            unused = [s for s in meshes if f"{s}.vertex_positions" not in keys]
            if unused:
                raise ValueError(f"targets.synthetic.meshes names {unused}, whose vertex_positions are not parameters")
        if self.geometry.remesh_at:
            if not any(k.endswith(".vertex_positions") for k in keys):
                raise ValueError("geometry.remesh_at remeshes optimized meshes: the job has no shape parameter "
                                 "(<shape id>.vertex_positions)")
            late = [k for k in self.geometry.remesh_at if k >= self.iterations]
            if late:
                raise ValueError(f"geometry.remesh_at {late}: a remesh comes before an iteration of the run, at most "
                                 f"iterations - 1 = {self.iterations - 1}")
        if self.optimizer in SECOND_ORDER and self.loss != "l2":
            raise ValueError(f"optimizer {self.optimizer!r} models the l2 loss; got loss {self.loss!r}")
        if self.hessian not in ("auto", "successive") and self.optimizer == "adam":
            raise ValueError(f"hessian {self.hessian!r} is a second-order optimizer's; the optimizer is "
                             f"{self.optimizer!r}")
        if self.jacobian == "differential-field" and self.method in (Method.DIRECT, Method.RADIANCE_CACHE):
            raise ValueError(f"jacobian 'differential-field' trains dL_theta; method {self.method!r} never has one")
        return self


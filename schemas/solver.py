"""Typed configuration of the solver: neural fields and their training (the same text documents the job API).

Sizes are chosen for 2 CPU cores. The paper uses 3 hidden layers of 256 neurons on a GPU; here a
training step evaluates each field at ~10^5 points (N residual points x M incident samples), and a
256-wide layer costs 16x the multiply-adds of a 64-wide one, which would put one step above a
second. The hash grid, not the MLP, dominates a 64-wide step (see bench/), so its table is kept
at 2^15 entries per level: the scenes here are small and smooth, and the images 64-256 pixels wide.
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class HashGridConfig(BaseModel):
    """Multiresolution hash encoding of position (Müller et al. 2022), on positions normalised to
    the unit cube by the scene's bounding box."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    n_levels: int = Field(8, ge=1, le=24, description="Number of grid resolutions.")
    features_per_level: int = Field(2, ge=1, le=8, description="Learned features stored per grid vertex.")
    log2_hashmap_size: int = Field(15, ge=8, le=22,
                                   description="log2 of the table size per level; coarse levels that fit are dense.")
    base_resolution: int = Field(8, ge=2, le=1024, description="Grid resolution of the coarsest level.")
    per_level_scale: float = Field(1.6, ge=1.0, le=4.0,
                                   description="Resolution growth factor between consecutive levels.")

    @property
    def output_dim(self) -> int:
        return self.n_levels * self.features_per_level


class MLPConfig(BaseModel):
    """Fully connected network after the encodings (ReLU hidden activations, linear output)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    hidden_width: int = Field(64, ge=4, le=1024, description="Neurons per hidden layer (paper: 256).")
    hidden_layers: int = Field(3, ge=1, le=8, description="Number of hidden layers (paper: 3).")


class FieldConfig(BaseModel):
    """One neural field: inputs, encodings and network."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    encoding: HashGridConfig = Field(default_factory=HashGridConfig,
                                     description="Encoding of the surface position x.")
    mlp: MLPConfig = Field(default_factory=MLPConfig, description="Network after the encodings.")
    direction_sh_degree: int = Field(4, ge=0, le=4,
                                     description="Spherical-harmonics degree of the outgoing direction "
                                                 "(degree d gives d^2 features; 0 = radiance independent of direction).")
    use_normal: bool = Field(True, description="Feed the surface normal (tells the two sides of thin surfaces apart).")


class PoolConfig(BaseModel):
    """Reuse of residual batches across training steps (geometry is fixed in every job, so points,
    incident rays, hits and encoding lookups are drawn once per batch; only BSDF and emitter
    values are re-evaluated after a parameter step). See ``services/solver/training/pool.py``."""

    model_config = ConfigDict(extra="forbid")

    enabled: bool = Field(True, description="Train on a pool of residual batches, both fields on the same batch "
                                            "(false: two fresh batches per step, one per field, as in the paper's "
                                            "Sec. 6.1).")
    chunks: int = Field(8, ge=1, le=256,
                        description="Batches kept in the pool; step s trains on batch s mod chunks. Memory: "
                                    "chunks x N x M incident samples (~0.4 KiB each).")
    reuse: int = Field(4, ge=1, le=10000,
                       description="Steps a batch is trained on before it is redrawn (1: fresh samples every "
                                   "step). Sampling and encoding cost 1/reuse of a fresh step; the fields see "
                                   "1/reuse as many independent samples.")


class HeadConfig(BaseModel):
    """The many-parameter head of ``dL_theta`` (paper Sec. 8; ``services/solver/fields/head.py``):
    ``R`` basis functions ``B_r(x, ω)`` (RGB each) and a learned coefficient matrix ``C`` (R x P)
    with ``∂L/∂p_k ≈ Σ_r B_r C[r, k]`` for the indirect part of the derivative; the BSDF's own
    derivative (a texel's local effect) is computed exactly. Its size does not grow with P, so
    it carries textures. Only ``ndrf-rhs`` uses it."""

    model_config = ConfigDict(extra="forbid")

    rank: int = Field(16, ge=1, le=256, description="R: basis functions (each RGB) of the head.")
    scalars_per_step: int = Field(32, ge=1, le=4096,
                                  description="S: parameter indices k whose residual a training step takes "
                                              "(drawn among the scalars the step's secondary hits depend on).")


class TrainingConfig(BaseModel):
    """How ``L_phi`` and ``dL_theta`` are trained by their residuals (paper Sec. 4.1, 6.1)."""

    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)

    residual_points: int = Field(4096, ge=64, le=262144,
                                 description="N: residual points (x, ω_o) per training step and per residual (Eq. 8).")
    incident_samples: int = Field(4, ge=1, le=256,
                                  description="M: incident samples per residual point, each one emitter and one "
                                              "BSDF sample combined by MIS (Eq. 9). The fields are queried at "
                                              "N·M points per step: four cost a quarter of sixteen, and the "
                                              "residual's noise averages over steps (bench/ndrf_cost.py).")
    camera_points: float = Field(0.25, ge=0.0, le=0.9,
                                 description="Fraction of residual points placed where the cameras look (first "
                                             "hits of primary rays, ω_o towards the camera), the rest uniform by "
                                             "area (the paper: 0). Same fixed point; the networks' error moves to "
                                             "where gradients are queried, which view-dependent (glossy) "
                                             "derivatives need.")
    warmup_steps: int = Field(400, ge=0, le=100000,
                              description="Training steps before the first gradient is computed (with "
                                          "adaptive_steps: at most this many).")
    steps_per_iteration: int = Field(4, ge=0, le=10000,
                                     description="Fine-tuning steps per inverse-rendering iteration (Sec. 6.1; "
                                                 "with adaptive_steps: at most this many). A warm network "
                                                 "after a small parameter step needs few (bench/ndrf_cost.py, "
                                                 "bench/pareto.py --variant ndrf).")
    adaptive_steps: bool = Field(False,
                                 description="Let the residual norms decide the steps: the warm-up stops when "
                                             "both residuals plateau, fine-tuning when they are back at their "
                                             "plateau after a parameter step (services/solver/training/schedule.py).")
    min_warmup_steps: int = Field(100, ge=0, le=100000, description="Adaptive warm-up: at least this many steps.")
    min_steps_per_iteration: int = Field(1, ge=0, le=10000,
                                         description="Adaptive fine-tuning: at least this many steps per iteration.")
    plateau_window: int = Field(40, ge=2, le=10000,
                                description="Adaptive steps: steps per window when the warm-up compares residual "
                                            "norms (fine-tuning averages over a tenth of it, at least 2).")
    plateau_tolerance: float = Field(0.05, gt=0, le=1.0,
                                     description="Adaptive steps: a residual has plateaued when its window mean fell "
                                                 "by less than this fraction, or the field's own residual is below "
                                                 "this fraction of the training loss; fine-tuning stops when the "
                                                 "residual exceeds its value before the parameter step by at most "
                                                 "this fraction of the loss.")
    learning_rate: float = Field(5e-3, gt=0, le=1.0, description="Adam learning rate of both fields.")
    learning_rate_decay: float = Field(0.999, gt=0, le=1.0,
                                       description="Multiplicative learning-rate decay per training step "
                                                   "(floored at 10% of the initial rate).")
    weight_averaging: float | None = Field(0.99, ge=0.0, lt=1.0,
                                           description="β of an exponential moving average of each field's weights "
                                                       "(Polyak averaging; services/solver/fields/averaging.py): "
                                                       "queries read the average, training the live weights; it "
                                                       "restarts when the parameters change. Null: query the live "
                                                       "weights.")
    semi_gradient: bool = Field(True,
                                description="Minimise ||LHS - sg(RHS)||² (the right-hand side is a fixed target "
                                            "each step) instead of back-propagating through both sides of the "
                                            "residual. Converges faster; the fixed point is the same.")
    residual_clip: float | None = Field(20.0, gt=0, le=1e6,
                                        description="Residual entries beyond this many output scales enter the "
                                                    "loss linearly (Huber) instead of squared: a firefly cannot "
                                                    "dominate a step. Null: plain least squares.")
    max_grad_norm: float | None = Field(100.0, gt=0, le=1e9,
                                        description="Clip the norm of each field's gradient per step (null: off). "
                                                    "Steps with a non-finite loss or gradient are skipped.")
    delta_depth: int = Field(8, ge=0, le=64,
                             description="Maximum number of ideal-specular bounces a ray follows to its first "
                                         "non-delta surface.")
    pool: PoolConfig = Field(default_factory=PoolConfig, description="Reuse of residual batches across steps.")
    head: HeadConfig | None = Field(None, description="dL_theta as the many-parameter head (R basis functions and "
                                                      "an R x P coefficient matrix; paper Sec. 8), which lets "
                                                      "ndrf-rhs carry textures. Null: one output per scalar and "
                                                      "channel (the default).")
    radiance: FieldConfig = Field(default_factory=FieldConfig, description="The radiance field L_phi.")
    differential: FieldConfig = Field(default_factory=FieldConfig,
                                      description="The differential radiance field dL_theta (one output per active scalar "
                                                          "and RGB channel it can change; see effects.merge_channels).")

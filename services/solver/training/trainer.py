"""Training of ``L_phi`` and ``dL_theta`` by residual minimisation (paper Sec. 4, 6.1).

Each step takes one Adam step on each field:

    loss_phi   = ||r_phi||²    (Eq. 5, 8)      trains L_phi
    loss_theta = ||r_theta||²  (Eq. 6, 7, 8)   trains dL_theta, with sg(L_phi)

With ``pool.enabled`` (default) both residuals are estimated on one batch of a
:class:`~services.solver.training.pool.ResidualPool` (points, rays, hits and encoding lookups reused
across steps) and ``L_phi(x')`` is evaluated once for both right-hand sides; otherwise each step
draws two fresh, independent batches, one per residual (the paper's Sec. 6.1). The fixed point is
the same: ``L_phi`` is a constant of ``r_theta`` either way.

With ``semi_gradient`` (default) the right-hand side is a fixed target within a step, as in
fitted value iteration; otherwise the gradient flows through both sides (Neural Radiosity). The
two residual norms are the accuracy proxy reported per iteration.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

import numpy as np
import torch

from schemas.solver import TrainingConfig
from services.solver.estimators.methods.base import Fields, GradientMethod
from services.solver.estimators.problem import Problem
from services.solver.fields.averaging import WeightAverage
from services.solver.fields.field import NeuralField
from services.solver.fields.head import ParameterHead
from services.solver.scene.effects import Effects
from services.solver.seeds import derive_seed
from services.solver.training.head import HeadBatch, draw_head_batch, head_lhs, head_rhs_samples
from services.solver.training.pool import ResidualPool
from services.solver.training.residuals import (
    ResidualBatch,
    debiased_residual,
    differential_rhs,
    differential_rhs_samples,
    draw_batch,
    incident_radiance,
    radiance_rhs_samples,
    residual_loss,
)
from services.solver.training.schedule import StepSchedule
from services.solver.training.steps import StepStats

log = logging.getLogger(__name__)


def _stats(radiance: tuple | None, differential: tuple | None, seconds: float, radiance_seconds: float,
           differential_seconds: float, batch: tuple[int, int] | None = None) -> StepStats:
    """StepStats from the ``(loss, residual)`` pairs of the two fields (None: not trained)."""
    return StepStats(radiance[0] if radiance else None, differential[0] if differential else None, seconds,
                     radiance_seconds, differential_seconds, radiance[1] if radiance else None,
                     differential[1] if differential else None, batch)


def _channel_scale(values: torch.Tensor, floor_ratio: float = 1e-2) -> torch.Tensor:
    """Per-channel RMS of ``values`` ``(N, C)``, floored at a fraction of the largest channel."""
    rms = values.square().mean(0).sqrt()
    floor = max(float(rms.max()) * floor_ratio, 1e-12)
    return rms.clamp_min(floor)


class FieldTrainer:
    """Owns the fields of one problem, their optimizers, and the training step counter."""

    def __init__(self, problem: Problem, config: TrainingConfig, *, radiance: bool, differential: bool, seed: int):
        self.problem = problem
        self.config = config
        self.seed = seed
        self.steps = 0
        lo, hi = problem.bbox
        #: dL_theta is the many-parameter head (``training.head``; services.solver.training.head)
        head = differential and config.head is not None
        if differential and not head and problem.layout.outputs == 0:
            raise ValueError("dL_theta has no output: no active scalar (see the chosen effects)")
        # each field is initialised from its own seed: training one does not change the other
        self.radiance = self._field(config.radiance, 3, lo, hi, "radiance") if radiance else None
        self.differential: NeuralField | None = None
        self.head: ParameterHead | None = None  # dL_theta as the many-parameter head, in place of differential
        if head:
            assert config.head is not None
            with torch.random.fork_rng(devices=[]):
                torch.manual_seed(derive_seed(self.seed, "init", "differential"))
                self.head = ParameterHead(config.differential, config.head.rank, problem.parameters.n, lo, hi)
        elif differential:
            self.differential = self._field(config.differential, problem.layout.outputs, lo, hi, "differential")
        self._head_batch: HeadBatch | None = None
        self.optimizers = {
            name: torch.optim.Adam(field.parameters(), lr=config.learning_rate, eps=1e-10, fused=True)
            for name, field in self.fields().items()
        }
        self.averages = ({name: WeightAverage(field, config.weight_averaging) for name, field in self.fields().items()}
                         if config.weight_averaging is not None else {})
        self.calibrated = {name: False for name in self.optimizers}
        self.last = StepStats(None, None, 0.0)
        self.schedule = StepSchedule(config)
        self.pool = None
        if config.pool.enabled:
            self.pool = ResidualPool(problem, config.residual_points, config.incident_samples,
                                     chunks=config.pool.chunks, reuse=config.pool.reuse,
                                     derivatives=self.differential is not None,
                                     fields=[f for f in self.fields().values() if isinstance(f, NeuralField)],
                                     seed=seed, camera_fraction=config.camera_points)

    def _field(self, config, channels: int, lo, hi, name: str) -> NeuralField:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(derive_seed(self.seed, "init", name))
            return NeuralField(config, channels, lo, hi)

    def fields(self) -> dict[str, NeuralField | ParameterHead]:
        """The fields being trained (live weights)."""
        pairs = (("radiance", self.radiance), ("differential", self.differential if self.head is None else self.head))
        return {name: f for name, f in pairs if f is not None}

    def queried(self) -> Fields:
        """The fields that gradients and images read: the weight averages (``weight_averaging``)
        or, without them, the live fields."""
        if not self.averages:
            return Fields(self.radiance, self.differential, self.head)
        pick = {name: average.average for name, average in self.averages.items()}
        radiance, differential = pick.get("radiance"), pick.get("differential")
        return Fields(radiance if isinstance(radiance, NeuralField) else None,
                      differential if isinstance(differential, NeuralField) else None,
                      differential if isinstance(differential, ParameterHead) else None)

    def _update_averages(self) -> None:
        if self.averages:
            values = self.problem.parameters.values()
            for average in self.averages.values():
                average.update(values)

    # ------------------------------------------------------------------ steps

    def _learning_rate(self) -> float:
        decay = self.config.learning_rate_decay ** self.steps
        return self.config.learning_rate * max(decay, 0.1)

    def _batch(self, kind: int, derivatives: bool) -> ResidualBatch:
        seed = derive_seed(self.seed, "train", self.steps, kind)
        return draw_batch(self.problem, self.config.residual_points, self.config.incident_samples, seed, derivatives,
                          self.config.camera_points)

    def _calibrate(self, name: str, field: NeuralField, direct: torch.Tensor) -> None:
        with torch.no_grad():
            field.output_scale.copy_(_channel_scale(direct.reshape(direct.shape[0], -1)))
        self.calibrated[name] = True
        log.debug("%s output scale %s", name, field.output_scale.tolist())

    def _step_field(self, name: str, field: NeuralField | ParameterHead, lhs_fn, rhs_fn,
                    batch: ResidualBatch | HeadBatch, scale: torch.Tensor | None = None) -> tuple[float, float]:
        """One Adam step on ``field``; ``rhs_fn`` gives the right-hand side's ``M`` terms
        ``(N, M, C)``; ``scale`` ``(C,)`` (default the field's output scale). Returns the training
        loss and the debiased residual (nan when skipped)."""
        scale = field.output_scale if scale is None else scale
        optimizer = self.optimizers[name]
        for group in optimizer.param_groups:
            group["lr"] = self._learning_rate()
        with torch.set_grad_enabled(not self.config.semi_gradient):
            rhs_samples = rhs_fn(batch)
            rhs_samples = rhs_samples.reshape(rhs_samples.shape[0], rhs_samples.shape[1], -1)
            rhs = rhs_samples.mean(1)
        lhs = lhs_fn(batch)
        lhs = lhs.reshape(lhs.shape[0], -1)
        loss, clipped = residual_loss(lhs, rhs, batch.weight, scale, self.config.residual_clip)
        self.problem.count_sanitized(f"{name}: residuals clipped", clipped)
        with torch.no_grad():
            residual = debiased_residual(lhs, rhs_samples, batch.weight, scale)
        optimizer.zero_grad(set_to_none=True)
        if not torch.isfinite(loss):
            self.problem.count_sanitized(f"{name}: steps skipped (non-finite loss)", 1)
            return float("nan"), float("nan")
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_(field.parameters(), self.config.max_grad_norm or float("inf"))
        if not torch.isfinite(norm):
            self.problem.count_sanitized(f"{name}: steps skipped (non-finite gradient)", 1)
            optimizer.zero_grad(set_to_none=True)
            return float("nan"), float("nan")
        if self.config.max_grad_norm is not None and float(norm) > self.config.max_grad_norm:
            self.problem.count_sanitized(f"{name}: gradient norms clipped", 1)
        optimizer.step()
        return float(loss.detach()), residual

    def step(self) -> StepStats:
        """One Adam step on each field (Sec. 6.1)."""
        if self.pool is not None:
            return self._pool_step()
        start = time.perf_counter()
        radiance_step = differential = None
        if self.radiance is not None:
            batch = self._batch(0, derivatives=False)
            if not self.calibrated["radiance"]:
                self._calibrate("radiance", self.radiance, batch.emitted.mean(1))
            radiance_step = self._step_field("radiance", self.radiance, lambda b: self.radiance(b.points),
                                             lambda b: radiance_rhs_samples(b, self.radiance), batch)
        middle = time.perf_counter()
        if self.head is not None:
            differential = self._head_step()
        elif self.differential is not None:
            batch = self._batch(1, derivatives=True)
            layout = self.problem.layout
            if not self.calibrated["differential"]:
                self._calibrate("differential", self.differential,
                                layout.pack(differential_rhs(batch, self.radiance, None, layout)))
            differential = self._step_field(
                "differential", self.differential, lambda b: self.differential(b.points),
                lambda b: layout.pack(differential_rhs_samples(b, self.radiance, self.differential, layout)), batch)
        self.steps += 1
        self._update_averages()
        end = time.perf_counter()
        self.last = _stats(radiance_step, differential, end - start, middle - start, end - middle)
        return self.last

    def _pool_step(self) -> StepStats:
        """Both fields on one pooled batch; the fields at ``x'`` are evaluated once (no grad: the
        semi-gradient right-hand sides), before either field's Adam step."""
        assert self.pool is not None  # step() calls this only with a pool
        start = time.perf_counter()
        batch = self.pool.batch(self.steps)
        layout, radiance = self.problem.layout, self.radiance
        differential = self.differential
        if radiance is not None and not self.calibrated["radiance"]:
            self._calibrate("radiance", radiance, batch.emitted.mean(1))
        if differential is not None and not self.calibrated["differential"]:
            self._calibrate("differential", differential, layout.pack(differential_rhs(batch, radiance, None, layout)))
        shared = self.config.semi_gradient
        with torch.no_grad():
            l_hit = incident_radiance(batch, radiance) if shared and radiance is not None else None
            dl_hit = incident_radiance(batch, differential) if shared and differential is not None else None
        radiance_step = diff = None
        if radiance is not None:
            radiance_step = self._step_field("radiance", radiance, lambda b: radiance(b.points),
                                             lambda b: radiance_rhs_samples(b, radiance, l_hit), batch)
        middle = time.perf_counter()
        if self.head is not None:
            diff = self._head_step()
        elif differential is not None:
            diff = self._step_field(
                "differential", differential, lambda b: differential(b.points),
                lambda b: layout.pack(differential_rhs_samples(b, radiance, differential, layout, l_hit, dl_hit)),
                batch)
        batch_id = self.pool.batch_id(self.steps)
        self.steps += 1
        self._update_averages()
        end = time.perf_counter()
        self.last = _stats(radiance_step, diff, end - start, middle - start, end - middle, batch_id)
        return self.last

    def _head_step(self) -> tuple[float, float]:
        """One Adam step on the many-parameter head (``services.solver.training.head``): a batch
        with its drawn scalars, redrawn every ``pool.reuse`` steps and whenever the parameters
        changed (its BSDF derivatives were evaluated at the old values)."""
        head, config = self.head, self.config
        assert head is not None and config.head is not None
        batch = self._head_batch
        if (batch is None or self.steps % config.pool.reuse == 0
                or not np.array_equal(batch.values, self.problem.parameters.values())):
            batch = self._head_batch = draw_head_batch(
                self.problem, config.residual_points, config.incident_samples, config.head.scalars_per_step,
                derive_seed(self.seed, "head", self.steps), config.camera_points)
        if not self.calibrated["differential"]:
            with torch.no_grad():
                direct = head_rhs_samples(batch, head, self.radiance, indirect=False).mean(1)
            head.calibrate(_channel_scale(direct.reshape(-1, 3)))
            self.calibrated["differential"] = True
        return self._step_field("differential", head, lambda b: head_lhs(b, head),
                                lambda b: head_rhs_samples(b, head, self.radiance), batch,
                                scale=head.output_scale.repeat(len(batch.scalars)))

    def train(self, steps: int, on_step: Callable[[StepStats], None] | None = None) -> list[StepStats]:
        """``steps`` steps; ``on_step`` sees each one's statistics (and may raise to stop)."""
        out = []
        for _ in range(steps):
            out.append(self.step())
            if on_step is not None:
                on_step(out[-1])
        return out

    def train_iteration(self, on_step: Callable[[StepStats], None] | None = None) -> list[StepStats]:
        """The training of one inverse-rendering iteration: the warm-up first, then fine-tuning,
        fixed or adaptive (:class:`~services.solver.training.schedule.StepSchedule`)."""
        return self.schedule.run(self, on_step)

    def check_finite(self) -> None:
        """Raise if a field's weights are no longer finite (the skip guards make this a bug, not
        a state to continue from)."""
        for name, f in self.fields().items():
            if not all(torch.isfinite(p).all() for p in f.parameters()):
                raise FloatingPointError(f"the weights of {'L_phi' if name == 'radiance' else 'dL_theta'} became "
                                         f"non-finite after {self.steps} training steps")

    # ------------------------------------------------------------- checkpoints

    def state_dict(self) -> dict:
        return {
            "steps": self.steps,
            "calibrated": dict(self.calibrated),
            "fields": {name: f.state_dict() for name, f in self.fields().items()},
            "optimizers": {name: o.state_dict() for name, o in self.optimizers.items()},
            "schedule": self.schedule.state_dict(),
            "averages": {name: a.state_dict() for name, a in self.averages.items()},
            "layout": layout_json(self.problem.layout),  # what dL_theta's outputs mean (views, warm starts)
        }

    def load_state_dict(self, state: dict) -> None:
        self.steps = int(state["steps"])
        self.calibrated.update(state["calibrated"])
        self.schedule.load_state_dict(state.get("schedule", {"warmed": self.steps > 0}))
        for name, f in self.fields().items():
            f.load_state_dict(state["fields"][name])
            self.optimizers[name].load_state_dict(state["optimizers"][name])
        saved = state.get("averages", {})
        for name, average in self.averages.items():
            if name in saved:
                average.load_state_dict(saved[name])
            else:  # a checkpoint from before weight averaging: start the average at the live weights
                average.average.load_state_dict(self.fields()[name].state_dict())


def layout_json(layout) -> dict:
    """The derivative layout as plain data: the active scalars and each one's RGB channels."""
    return {"scalars": [int(i) for i in layout.scalars], "channels": [[int(c) for c in cs] for cs in layout.channels]}


def trained_fields(method: GradientMethod, effects: Effects | None, *, radiance: bool = False) -> tuple[bool, bool]:
    """Which fields a run of ``method`` (as its effects shape it) trains: ``(L_phi, dL_theta)``.

    ``dL_theta`` when the method queries it; ``L_phi`` when the method queries it, when
    ``dL_theta`` is trained and its residual contains ``∫ (∂f) L_phi`` (the effects decide; without
    them: whenever ∂f is attached, which it is), or when asked (``radiance``: the candidate image
    comes from it)."""
    differential = method.needs_differential
    for_residual = effects.radiance_field.value if effects is not None else True
    return radiance or method.needs_radiance or (differential and bool(for_residual)), differential


def trainer_for(problem: Problem, method: GradientMethod, config: TrainingConfig, seed: int, *,
                radiance: bool = False) -> FieldTrainer | None:
    """The trainer of exactly the fields ``method`` uses (none for ``direct`` and ``prb``), for
    a gradient evaluated outside a run (a run's trainer follows its recipe)."""
    radiance, differential = trained_fields(method, problem.effects, radiance=radiance)
    if not (radiance or differential):
        return None
    return FieldTrainer(problem, config, radiance=radiance, differential=differential, seed=seed)


def fields_of(trainer: FieldTrainer | None) -> Fields:
    """The fields a method queries (:meth:`FieldTrainer.queried`; none without a trainer)."""
    return Fields() if trainer is None else trainer.queried()

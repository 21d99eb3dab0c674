"""Training of ``L_phi`` and ``dL_theta`` by residual minimisation (paper Sec. 4, 6.1).

Each step draws two independent batches, one per residual, and takes one Adam step on each field:

    loss_phi   = ||r_phi||²    (Eq. 5, 8)      trains L_phi
    loss_theta = ||r_theta||²  (Eq. 6, 7, 8)   trains dL_theta, with sg(L_phi)

With ``semi_gradient`` (default) the right-hand side is a fixed target within a step, as in
fitted value iteration; otherwise the gradient flows through both sides (Neural Radiosity). The
two residual norms are the accuracy proxy reported per iteration.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

import torch

from schemas.solver import TrainingConfig
from services.estimators.context import Problem
from services.estimators.residuals import (ResidualBatch, differential_rhs, draw_batch, primal_rhs,
                                           residual_loss)
from services.fields.field import NeuralField
from services.seeds import derive_seed

log = logging.getLogger(__name__)


@dataclass
class StepStats:
    """One training step: residual norms (in output-scale units) and seconds (in total and per
    field, sampling included)."""

    primal_loss: float | None
    differential_loss: float | None
    seconds: float
    radiance_seconds: float = 0.0
    differential_seconds: float = 0.0


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
        if differential and problem.layout.outputs == 0:
            raise ValueError("dL_theta has no output: no active scalar (see the effect plan)")
        # each field is initialised from its own seed: training one does not change the other
        self.radiance = self._field(config.radiance, 3, lo, hi, "radiance") if radiance else None
        self.differential = (self._field(config.differential, problem.layout.outputs, lo, hi, "differential")
                             if differential else None)
        self.optimizers = {
            name: torch.optim.Adam(field.parameters(), lr=config.learning_rate, eps=1e-10)
            for name, field in self.fields().items()
        }
        self.calibrated = {name: False for name in self.optimizers}
        self.last = StepStats(None, None, 0.0)

    def _field(self, config, channels: int, lo, hi, name: str) -> NeuralField:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(derive_seed(self.seed, "init", name))
            return NeuralField(config, channels, lo, hi)

    def fields(self) -> dict[str, NeuralField]:
        return {name: f for name, f in (("radiance", self.radiance), ("differential", self.differential)) if f is not None}

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

    def _step_field(self, name: str, field: NeuralField, lhs_fn, rhs_fn, batch: ResidualBatch) -> float:
        optimizer = self.optimizers[name]
        for group in optimizer.param_groups:
            group["lr"] = self._learning_rate()
        with torch.set_grad_enabled(not self.config.semi_gradient):
            rhs = rhs_fn(batch)
        lhs = lhs_fn(batch)
        loss, clipped = residual_loss(lhs.reshape(lhs.shape[0], -1), rhs.reshape(rhs.shape[0], -1), batch.weight,
                                      field.output_scale, self.config.residual_clip)
        self.problem.count_sanitized(f"{name}: residuals clipped", clipped)
        optimizer.zero_grad(set_to_none=True)
        if not torch.isfinite(loss):
            self.problem.count_sanitized(f"{name}: steps skipped (non-finite loss)", 1)
            return float("nan")
        loss.backward()
        norm = torch.nn.utils.clip_grad_norm_(field.parameters(), self.config.max_grad_norm or float("inf"))
        if not torch.isfinite(norm):
            self.problem.count_sanitized(f"{name}: steps skipped (non-finite gradient)", 1)
            optimizer.zero_grad(set_to_none=True)
            return float("nan")
        if self.config.max_grad_norm is not None and float(norm) > self.config.max_grad_norm:
            self.problem.count_sanitized(f"{name}: gradient norms clipped", 1)
        optimizer.step()
        return float(loss.detach())

    def step(self) -> StepStats:
        """One Adam step on each field (separate sample sets, Sec. 6.1)."""
        start = time.perf_counter()
        primal = differential = None
        if self.radiance is not None:
            batch = self._batch(0, derivatives=False)
            if not self.calibrated["radiance"]:
                self._calibrate("radiance", self.radiance, batch.emitted.mean(1))
            primal = self._step_field("radiance", self.radiance, lambda b: self.radiance(b.points),
                                      lambda b: primal_rhs(b, self.radiance), batch)
        middle = time.perf_counter()
        if self.differential is not None:
            batch = self._batch(1, derivatives=True)
            layout = self.problem.layout
            if not self.calibrated["differential"]:
                self._calibrate("differential", self.differential,
                                layout.pack(differential_rhs(batch, self.radiance, None, layout)))
            differential = self._step_field(
                "differential", self.differential, lambda b: self.differential(b.points),
                lambda b: layout.pack(differential_rhs(b, self.radiance, self.differential, layout)), batch)
        self.steps += 1
        end = time.perf_counter()
        self.last = StepStats(primal, differential, end - start, middle - start, end - middle)
        return self.last

    def train(self, steps: int) -> list[StepStats]:
        return [self.step() for _ in range(steps)]

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
        }

    def load_state_dict(self, state: dict) -> None:
        self.steps = int(state["steps"])
        self.calibrated.update(state["calibrated"])
        for name, f in self.fields().items():
            f.load_state_dict(state["fields"][name])
            self.optimizers[name].load_state_dict(state["optimizers"][name])

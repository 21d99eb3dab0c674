"""How many training steps an inverse-rendering iteration takes (paper Sec. 5 step 1, Sec. 6.1).

Fixed (``training.adaptive_steps = false``): ``warmup_steps`` before the first iteration, then
``steps_per_iteration`` per iteration. Adaptive: those two become caps, and the residual norms
(Eq. 7, 8) decide:

* **warm-up** stops when both fields' residuals have plateaued. The measure is the debiased
  residual (the field's own residual, the right-hand side's Monte Carlo noise removed:
  :func:`~services.solver.training.residuals.debiased_residual`) averaged over a window of
  ``plateau_window`` steps (fresh batches only: a batch trained on before has part of its noise
  fitted). A field has plateaued when that is below ``plateau_tolerance`` times the training loss
  (what is left of its error is buried in the noise of its training targets) or fell by less than
  ``plateau_tolerance`` (relative) since the previous window (it stopped improving). The training
  loss alone is a poor measure: it is mostly that noise, and flattens long before the field does;
* **fine-tuning** after a parameter step continues until the fields are back at their plateau:
  on a pooled batch seen before, the debiased residual now minus the one it had at its previous use
  (same samples, so the noise cancels and only the change shows), in units of that previous loss,
  averaged over the last ``plateau_window // 10`` (at least 2) steps, is at most
  ``plateau_tolerance``. Without a pool there is no same-batch reference, and fine-tuning takes
  ``steps_per_iteration`` steps.

At least ``min_steps_per_iteration`` steps are taken per iteration and ``min_warmup_steps`` in
the warm-up.
"""

from __future__ import annotations

import logging
import math

import numpy as np

from schemas.solver import TrainingConfig
from services.solver.training.steps import Steps, StepStats

log = logging.getLogger(__name__)

_FIELDS = ("radiance", "differential")


def _value(stats: StepStats, field: str, kind: str) -> float | None:
    v = getattr(stats, f"{field}_{kind}")
    return v if v is not None and math.isfinite(v) else None


class StepSchedule:
    """Decides the training steps of each iteration for one trainer (state is checkpointed)."""

    def __init__(self, config: TrainingConfig):
        self.config = config
        self.warmed = False
        self.previous: dict[tuple[int, int], dict[str, tuple[float, float]]] = {}  # batch -> field -> (loss, res)
        self.history: list[int] = []  # steps taken per iteration (the warm-up first)
        self._on_step = None

    # ------------------------------------------------------------------ public

    def run(self, trainer: Steps, on_step=None) -> list[StepStats]:
        """Train for the current iteration; returns the steps' statistics. ``on_step`` sees each
        step (the loop's stop check and progress report; it may raise to stop)."""
        self._on_step = on_step
        c = self.config
        if not c.adaptive_steps:
            stats = trainer.train(c.steps_per_iteration if self.warmed or trainer.steps else c.warmup_steps,
                                  on_step)
        elif not self.warmed and trainer.steps == 0:
            stats = self._warmup(trainer)
        else:
            stats = self._finetune(trainer)
        self.warmed = True
        self.history.append(len(stats))
        return stats

    def state_dict(self) -> dict:
        return {"warmed": self.warmed, "history": list(self.history),
                "previous": [[list(k), {f: list(v) for f, v in d.items()}] for k, d in self.previous.items()]}

    def load_state_dict(self, state: dict) -> None:
        self.warmed = bool(state.get("warmed", False))
        self.history = list(state.get("history", []))
        self.previous = {tuple(k): {f: tuple(v) for f, v in d.items()} for k, d in state.get("previous", [])}

    # ---------------------------------------------------------------- phases

    def _step(self, trainer: Steps) -> tuple[StepStats, dict[str, float], bool]:
        """One step; returns it, per field the change of its debiased residual since the batch's
        previous use in units of that use's loss (absent for a batch not seen before), and whether
        the batch was fresh (its debiased residual is then unbiased: a batch trained on before has
        part of its noise fitted)."""
        step = trainer.steps
        stats = trainer.step()
        if self._on_step is not None:
            self._on_step(stats)
        fresh = stats.batch is None or stats.batch[1] == step
        excess = {}
        if stats.batch is not None:
            before = self.previous.get(stats.batch, {})
            now = {}
            for field in _FIELDS:
                loss, res = _value(stats, field, "loss"), _value(stats, field, "residual")
                if loss is None or res is None:
                    continue
                now[field] = (loss, res)
                if field in before and before[field][0] > 0:
                    excess[field] = (res - before[field][1]) / before[field][0]
            self.previous[stats.batch] = now
            drawn = {k for k in self.previous if k[0] == stats.batch[0] and k != stats.batch}
            for k in drawn:  # a redrawn slot's old batch will not come back
                del self.previous[k]
        return stats, excess, fresh

    def _warmup(self, trainer: Steps) -> list[StepStats]:
        c = self.config
        window = max(1, c.plateau_window)
        stats: list[StepStats] = []
        previous: dict[str, float] = {}
        while len(stats) < c.warmup_steps:
            block = [self._step(trainer) for _ in range(min(window, c.warmup_steps - len(stats)))]
            stats += [b[0] for b in block]
            now, plateau = {}, []
            for field in _FIELDS:
                losses = [v for s, _, _ in block if (v := _value(s, field, "loss")) is not None]
                residuals = [v for s, _, fresh in block if fresh and (v := _value(s, field, "residual")) is not None]
                if not losses or not residuals:
                    continue
                loss, residual = float(np.mean(losses)), float(np.mean(residuals))
                now[field] = residual
                buried = residual <= c.plateau_tolerance * loss           # within the targets' noise
                flat = field in previous and residual >= (1 - c.plateau_tolerance) * previous[field]
                plateau.append(buried or flat)
            previous = now
            if plateau and all(plateau) and len(stats) >= c.min_warmup_steps:
                log.info("warm-up: residuals plateaued after %d steps (debiased residuals %s)", len(stats), now)
                break
        return stats

    def _finetune(self, trainer: Steps) -> list[StepStats]:
        c = self.config
        recent = max(2, c.plateau_window // 10)
        stats: list[StepStats] = []
        excesses: dict[str, list[float]] = {field: [] for field in _FIELDS}
        while len(stats) < c.steps_per_iteration:
            s, excess, _ = self._step(trainer)
            stats.append(s)
            for field, e in excess.items():
                excesses[field].append(e)
            if len(stats) < c.min_steps_per_iteration:
                continue
            trained = [f for f in _FIELDS if _value(s, f, "loss") is not None]
            if trained and all(excesses[f] and np.mean(excesses[f][-recent:]) <= c.plateau_tolerance for f in trained):
                break
        return stats

"""Adaptive training steps (services/solver/training/schedule.py) on scripted residual norms."""

from __future__ import annotations

from services.solver.training.steps import StepStats


class ScriptedTrainer:
    """Steps whose losses and debiased residuals follow ``script(step, batch)``; pooled batches
    cycle over ``chunks`` slots and are redrawn after ``reuse`` uses, like the pool."""

    def __init__(self, script, chunks=4, reuse=4):
        self.script, self.chunks, self.reuse, self.steps = script, chunks, reuse, 0

    def step(self):
        s = self.steps
        batch = (s % self.chunks, s - ((s // self.chunks) % self.reuse) * self.chunks)
        loss, res = self.script(s, batch)
        self.steps += 1
        return StepStats(loss, loss, 0.0, radiance_residual=res, differential_residual=res, batch=batch)

    def train(self, n, on_step=None):
        return [self.step() for _ in range(n)]


def _schedule(**overrides):
    from schemas.solver import TrainingConfig
    from services.solver.training.schedule import StepSchedule

    config = dict(adaptive_steps=True, warmup_steps=2000, steps_per_iteration=20, min_warmup_steps=40,
                  plateau_window=20, plateau_tolerance=0.05)
    return StepSchedule(TrainingConfig(**(config | overrides)))


def test_warmup_stops_when_the_residual_plateaus_and_not_before():
    # noise floor 1.0; the field's own residual decays as 10 / (1 + step / 20)²
    trainer = ScriptedTrainer(lambda s, b: (1.0 + 10 / (1 + s / 20) ** 2, 10 / (1 + s / 20) ** 2))
    schedule = _schedule()
    stats = schedule.run(trainer)
    # the residual falls below 5% of the loss (about 5% of the noise floor) at step 256
    assert 256 <= len(stats) <= 300


def test_fixed_steps_without_adaptivity():
    trainer = ScriptedTrainer(lambda s, b: (1.0, 0.0))
    schedule = _schedule(adaptive_steps=False, warmup_steps=30, steps_per_iteration=5)
    assert [len(schedule.run(trainer)) for _ in range(3)] == [30, 5, 5]


def test_finetuning_stops_once_the_fields_are_back_on_their_plateau():
    """After a parameter step the same batches show a higher residual, decaying with training."""
    state = {"jump_at": None}

    def script(s, b):
        if state["jump_at"] is None:
            return 1.0, 0.0
        excess = 0.5 * 0.7 ** (s - state["jump_at"])
        return 1.0 + excess, excess

    trainer = ScriptedTrainer(script)
    schedule = _schedule(warmup_steps=60, min_warmup_steps=60, min_steps_per_iteration=1)
    assert len(schedule.run(trainer)) == 60                    # flat from the start: the minimum
    assert len(schedule.run(trainer)) <= 3                     # nothing changed: back at once
    state["jump_at"] = trainer.steps
    taken = len(schedule.run(trainer))
    assert 7 <= taken <= 12                                    # 0.5 · 0.7^k <= 0.05 at k >= 7 (+ averaging)
    state["jump_at"] = trainer.steps - 100                     # long settled
    assert len(schedule.run(trainer)) <= 3


def test_finetuning_is_capped():
    trainer = ScriptedTrainer(lambda s, b: (1.0 + s, float(s)))   # never settles
    schedule = _schedule(warmup_steps=40, min_warmup_steps=40, steps_per_iteration=7)
    schedule.run(trainer)
    assert len(schedule.run(trainer)) == 7

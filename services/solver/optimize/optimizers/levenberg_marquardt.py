"""Levenberg-Marquardt steps in a trust region that follows the agreement of consecutive steps.

Update rule, at iteration ``k`` with gradient ``g_k``, curvature ``H_k`` (:mod:`.gauss_newton`) and
learning rate ``lr_k`` (the job's schedule)::

    Δ_k  = -(H_k + λ diag(H_k) + μ I)⁻¹ g_k          over the free scalars (:func:`damped_step`)
    c_k  = cos(Δ_k, Δ_{k-1})
    r_k  = r_{k-1} / 2        if c_k < 0                          (the step reversed)
           r_{k-1} · γ        if c_k > 1/2 and Δ_{k-1} was capped  (it keeps going the same way)
           r_{k-1}            otherwise
    r_k  = clip(r_k, lr_k, 20 · lr_0),        r_0 = s · lr_0
    Δ'   = Δ_k · min(1, r_k / max|Δ_k / u|)      u: the step units (1, or a rotation's, ``units``)
    p_{k+1} = p_k + clip(Δ', -τ (p_k - lower), τ (upper - p_k)),        τ = 1/2

The growth ``γ`` (``grow``, 3/2 by default) and the start ``s`` (``start``, 1 by default: the first
step is Adam's) are the recipe's: ``γ = 2`` and ``s = 4`` where most light leaves the scene and
the image is close to linear in the scalars (:mod:`services.solver.scene.closure`).

The last line is the fraction-to-the-boundary rule of interior-point methods: a step covers at
most half the way to a bound. Gauss-Newton's linear model overshoots where the image grows faster
than linearly in a scalar, and in a closed room the image grows as ``1/(1 - albedo)``: a step
that lands a wall on albedo 1 lands on infinite light (and noise without end). Approached this
way, a bound is reached only geometrically (an answer at a bound is still found to any accuracy).

Why this rule and not Marquardt's classic gain ratio: the classic rule compares the loss at
``p_k + Δ`` with the model's prediction, and with 1-spp Monte Carlo images both are noise near
the answer: the ratio is random, the radius collapses and the run stalls (measured on the bright
closed room). Consecutive *directions* are a robust signal. Far from the answer the Newton step
is bigger than the radius and keeps pointing the same way, so the radius grows geometrically (the
answer is reached in a few steps where Adam's steps are limited to the learning rate). Near it,
the noise makes consecutive steps reverse, and the radius halves down to the learning rate, which
the schedule decays: the steps then average the noise as Adam's do, so it neither stalls (the
radius never falls below ``lr_k``) nor wanders (a reversal halves it).

Reversals are counted: ``ρ_k = 0.8 ρ_{k-1} + 0.2 [c_k < 0]`` is the recent share of reversing
steps, about 0 while the steps make progress and 1/2 when the gradient's noise decides their
direction. Above :data:`NOISY` the steps are noise-dominated (:meth:`noise_dominated`, and the
count restarts): ``views_per_iteration: "auto"`` then doubles the batch, which halves the noise.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from services.solver.optimize.optimizers.base import ParameterOptimizer
from services.solver.optimize.optimizers.gauss_newton import damped_step, free_scalars

if TYPE_CHECKING:
    from services.solver.optimize.optimizers.curvature import Curvature

#: The default first radius and the largest, in units of ``lr_0``, and the default growth on agreeing
#: capped steps. The default first radius is Adam's first step. A faster start (4x, or growth 2)
#: reaches the open room's answer a step or two sooner and overshoots in the bright closed room
#: (``python -m bench.investigations.trust_growth``), which is why both are the recipe's.
INITIAL, GROW, RADIUS_CAP = 1.0, 1.5, 20.0
#: Cosine between consecutive steps above which they agree.
AGREE = 0.5
#: The recent share of reversing steps above which they are noise-dominated (pure noise: 1/2).
NOISY = 0.4
#: Decay of that share's moving average.
MEMORY = 0.8
#: The share of the way to a bound one step may cover.
TAU = 0.5


class LevenbergMarquardt(ParameterOptimizer):
    name = "levenberg-marquardt"
    needs_curvature = True

    def __init__(self, size: int, lr: float, damping: float, grow: float = GROW, start: float = INITIAL,
                 curvature: Curvature | None = None):
        if not lr > 0:
            raise ValueError(f"learning rate must be > 0, got {lr}")
        if damping < 0:
            raise ValueError(f"damping must be >= 0, got {damping}")
        if not 1 < grow <= 4:
            raise ValueError(f"trust-region growth must be in (1, 4], got {grow}")
        if not 1 <= start <= RADIUS_CAP:
            raise ValueError(f"trust-region start must be in [1, {RADIUS_CAP:g}] learning rates, got {start}")
        self.lr0, self.damping, self.grow = lr, damping, grow
        self.curvature = curvature
        self.radius = start * lr
        self.previous = np.zeros(size)
        self.capped = False
        self.reversals = 0.0
        self.noisy = False

    def step(self, p, gradient, lower, upper, *, lr, hessian=None, jacobians=None):
        if not lr > 0:
            raise ValueError(f"learning rate must be > 0, got {lr}")
        hessian = self.hessian(p, lr, hessian, jacobians)
        delta = damped_step(gradient, hessian, self.damping, free_scalars(p, gradient, lower, upper))
        norms = float(np.linalg.norm(delta) * np.linalg.norm(self.previous))
        cosine = float(delta @ self.previous) / norms if norms > 0 else 0.0
        if cosine < 0:
            self.radius /= 2
        elif cosine > AGREE and self.capped:
            self.radius *= self.grow
        self.radius = float(min(max(self.radius, lr), RADIUS_CAP * self.lr0))
        if norms > 0:
            self.reversals = MEMORY * self.reversals + (1 - MEMORY) * float(cosine < 0)
        self.noisy = self.reversals > NOISY
        if self.noisy:
            self.reversals = 0.0
        scaled = delta if self.units is None else delta / self.units   # the radius is in step units
        largest = float(np.max(np.abs(scaled))) if delta.size else 0.0
        self.capped = largest > self.radius
        if self.capped:
            delta = delta * (self.radius / largest)
        p = np.asarray(p, np.float64)
        delta = np.clip(delta, -TAU * (p - lower), TAU * (upper - p))
        self.previous = delta
        return np.clip(p + delta, lower, upper)

    def noise_dominated(self) -> bool:
        return self.noisy

    def refused(self) -> None:
        """A refused step halves the radius and is not the previous step of the next."""
        self.radius /= 2
        self.previous = np.zeros_like(self.previous)
        self.capped = False

    def describe(self) -> dict:
        return {"trust_radius": self.radius, "reversals": self.reversals}

    def state_dict(self) -> dict:
        state = {"radius": self.radius, "previous": self.previous.tolist(), "capped": self.capped,
                 "reversals": self.reversals, "noisy": self.noisy}
        if self.curvature is not None:
            state["curvature"] = self.curvature.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.radius = float(state["radius"])
        self.previous = np.asarray(state["previous"], np.float64)
        self.capped = bool(state["capped"])
        self.reversals = float(state["reversals"])
        self.noisy = bool(state["noisy"])
        if self.curvature is not None and "curvature" in state:
            self.curvature.load_state_dict(state["curvature"])

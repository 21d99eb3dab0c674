"""Coarse to fine: the loss of a geometry job on blurred images, the blur narrowing over the run.

A pose 0.06 off on a 0.15-wide mesh, or 15 degrees about its axis, overlaps its target's
silhouette in a thin sliver: the image loss's gradient then sees only the edges that already
overlap, and on the Stanford bunny (64x64, two views) it points the rotation the wrong way and
the Gauss-Newton steps stall (``docs/guide/geometry.md``). Blurring both the render and the
target by a Gaussian ``G_σ`` (:class:`~services.solver.estimators.losses.BlurredLoss`) widens every
edge to ``σ`` pixels, so the images overlap and the gradient points towards the target from
farther away; for a target the scene can render exactly, the blurred loss has the same minimum.
The blur narrows linearly over the first ``blur_share`` of the run, from ``blur_px`` to
``blur_end_px``, and stays there:

    σ_k = σ_0 + (σ_end - σ_0) · min(1, k / (share · K))           K: the job's iterations

Only on films of at least :data:`AUTO_MIN_FILM` pixels by default (below, measured, it misleads).
The Jacobian the curvature uses is ``G_σ J`` (the blurred loss's), and so is the residual of the
answer's floor. ``σ_end`` defaults to one pixel, not zero: measured on the bunny, the first steps on
the sharp loss after a blurred phase threw the translation from 0.004 back to 0.03.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from schemas.job import JobSpec

#: ``blur_px: "auto"`` for a pose: this share of the film's smaller side,
AUTO_SHARE = 1 / 16
#: on films whose smaller side has at least this many pixels. On ``pose-block`` at 24x24 a blur of
#: 1.5 px (to 1 or 0.375 px) or 3 px (to 0.5 px) turned the block 30-41 degrees the wrong way about
#: the view's axis on both seeds tried, where the sharp loss ended within 7 degrees: on a block a few
#: pixels wide a blur of a pixel or more erases what tells its rotations apart.
AUTO_MIN_FILM = 48


@dataclass(frozen=True)
class BlurSchedule:
    """``σ_k`` in pixels (module docstring); ``start == 0``: no blur."""

    start: float
    end: float
    until: int    # the iteration from which σ is ``end``

    def at(self, k: int) -> float:
        if self.start <= 0:
            return 0.0
        if k >= self.until:
            return self.end
        return self.start + (self.end - self.start) * k / max(self.until, 1)

    def to_json(self) -> dict:
        return {"start_px": self.start, "end_px": self.end, "until_iteration": self.until}


def resolve_blur(spec: JobSpec, pose: bool, shape: bool, film: Callable[[], tuple[int, int]],
                 decide) -> BlurSchedule | None:
    """The blur of a geometry job (None: none), with the decision and its reason. ``pose``/``shape``:
    whether the job optimizes a pose / vertex positions; ``film()``: the smallest target view's
    (width, height), asked only for a pose's ``auto``."""
    settings = spec.geometry
    if not (pose or shape):
        return None
    if settings.blur_px == "auto":
        if not pose:
            decide("blur", 0.0, "vertex positions: no blur (their LargeSteps steps already move whole regions)")
            return None
        side = min(film())
        if side < AUTO_MIN_FILM:
            decide("blur", 0.0, f"a film of {side} px (under {AUTO_MIN_FILM}): a blur would erase what tells a "
                                f"pose's rotations apart; the loss compares sharp images")
            return None
        start = round(side * AUTO_SHARE, 2)
        reason = (f"a pose: coarse to fine, a Gaussian of {start:g} px (a sixteenth of the film's {side} px) "
                  f"narrowing to {settings.blur_end_px:g} px over the first {settings.blur_share:.0%} of the "
                  f"iterations, so that a pose far from its target still overlaps it in the loss")
    else:
        start = float(settings.blur_px)
        reason = "the job's geometry.blur_px"
    if start <= 0:
        decide("blur", 0.0, "the job's geometry.blur_px is 0: the loss compares sharp images")
        return None
    schedule = BlurSchedule(start=start, end=min(settings.blur_end_px, start),
                            until=max(1, round(settings.blur_share * spec.iterations)))
    decide("blur", start, reason)
    return schedule

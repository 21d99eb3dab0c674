"""Path depth, and the path-traced candidate image ``y`` of Sec. 5, step 2 (and synthetic targets),
with Mitsuba's ``path`` integrator.

A :class:`PathDepth` is passed wherever a path is traced (the candidate, ``prb``, its Jacobian,
synthetic targets): there is no default depth below this module, so a truncation is always a
decision someone wrote down. The product's default is :data:`UNBIASED`, Mitsuba's own: unbounded
paths ended by Russian roulette from depth 5. Roulette is unbiased (a path it keeps is re-weighted
by the inverse of its survival probability); truncating at a fixed depth is not, and in a bright
closed room a depth of 12 misses a quarter of the light (``tests/unit/test_depth_bias.py``).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from services.solver.estimators.problem import Problem
from services.solver.sampling.passes import passes_for
from services.solver.seeds import derive_seed


@dataclass(frozen=True)
class PathDepth:
    """``max_depth``: the longest path (None: unbounded); ``rr_depth``: the depth from which Russian
    roulette ends paths (None: off). One of the two must end every path."""

    max_depth: int | None
    rr_depth: int | None

    def __post_init__(self):
        if self.max_depth is None and self.rr_depth is None:
            raise ValueError("a path depth needs max_depth or rr_depth: unbounded paths without Russian roulette "
                             "never end")
        for name in ("max_depth", "rr_depth"):
            value = getattr(self, name)
            if value is not None and value < 1:
                raise ValueError(f"{name} must be >= 1 or None, got {value}")

    @property
    def unbiased(self) -> bool:
        """Whether every bounce is estimated (no truncation)."""
        return self.max_depth is None

    def integrator_props(self) -> dict:
        """``max_depth`` and ``rr_depth`` as Mitsuba's integrators take them (-1: unbounded)."""
        max_depth = -1 if self.max_depth is None else self.max_depth
        rr_depth = self.rr_depth if self.rr_depth is not None else (self.max_depth or 0) + 1
        return {"max_depth": max_depth, "rr_depth": rr_depth}

    def integrator(self, kind: str) -> mi.Integrator:
        """A Mitsuba integrator of type ``kind`` (``path``, ``prb``) with this depth."""
        return mi.load_dict({"type": kind, **self.integrator_props()})

    def describe(self) -> str:
        depth = "unbounded" if self.max_depth is None else f"at most {self.max_depth} bounces"
        roulette = "no Russian roulette" if self.rr_depth is None else f"Russian roulette from depth {self.rr_depth}"
        bias = "unbiased" if self.unbiased else "truncated: biased where light takes more bounces"
        return f"{depth}, {roulette} ({bias})"


#: Mitsuba's default for every path it traces: unbounded, roulette from depth 5.
UNBIASED = PathDepth(None, 5)


def render(problem: Problem, *, spp: int, seed: int, depth: PathDepth, sensor: int = 0) -> np.ndarray:
    """Non-differentiable image of sensor ``sensor``: ``(H, W, 3)`` float32 (alpha dropped)."""
    integrator = depth.integrator("path")
    width, height = problem.scene.resolution(sensor)
    passes, per_pass = passes_for(width * height, spp)
    total = np.zeros((height, width, 3))
    with dr.suspend_grad():
        for k in range(passes):
            image = mi.render(problem.scene.scene, sensor=sensor, integrator=integrator, spp=per_pass,
                              seed=opaque_seed(derive_seed(seed, "path", k)))
            total += np.array(image, dtype=np.float64)[..., :3]
    return (total / passes).astype(np.float32)


def opaque_seed(seed: int) -> mi.UInt32:
    """A seed as an evaluated Dr.Jit value: a Python int would be a literal in the kernel, and a
    new literal is a new kernel (compiled again at every iteration)."""
    return dr.opaque(mi.UInt32, seed)


def missing_energy(problem: Problem, depth: PathDepth, *, seed: int, spp: int = 4, sensor: int = 0) -> float:
    """The fraction of the image's energy that ``depth`` misses against the unbiased render
    (Russian roulette from the same depth, unbounded): 0 for an unbiased depth. Used by the plan to
    warn about a truncation the job asked for."""
    if depth.unbiased:
        return 0.0
    truncated = float(render(problem, spp=spp, seed=seed, depth=depth, sensor=sensor).sum())
    full = float(render(problem, spp=spp, seed=seed, depth=PathDepth(None, depth.max_depth), sensor=sensor).sum())
    return max(0.0, (full - truncated) / max(full, 1e-30))

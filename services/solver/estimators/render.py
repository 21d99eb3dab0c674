"""The path-traced candidate image ``y`` of Sec. 5, step 2 (and synthetic targets), with Mitsuba's
``path`` integrator, Russian roulette off so that the image has no roulette noise."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from services.solver.estimators.problem import Problem
from services.solver.sampling.passes import passes_for
from services.solver.seeds import derive_seed


def path_integrator(max_depth: int) -> mi.Integrator:
    return mi.load_dict({"type": "path", "max_depth": max_depth, "rr_depth": max_depth + 1})


def render(problem: Problem, *, spp: int, seed: int, sensor: int = 0, max_depth: int = 12) -> np.ndarray:
    """Non-differentiable image of sensor ``sensor``: ``(H, W, 3)`` float32 (alpha dropped)."""
    integrator = path_integrator(max_depth)
    width, height = problem.scene.resolution(sensor)
    passes, per_pass = passes_for(width * height, spp)
    total = None
    with dr.suspend_grad():
        for k in range(passes):
            image = mi.render(problem.scene.scene, sensor=sensor, integrator=integrator, spp=per_pass,
                              seed=derive_seed(seed, "path", k))
            part = np.array(image, dtype=np.float64)[..., :3]
            total = part if total is None else total + part
    return (total / passes).astype(np.float32)


def converged_depth(problem: Problem, *, seed: int, tolerance: float = 1e-3, spp: int = 4, start: int = 8,
                    cap: int = 1024, sensor: int = 0) -> tuple[int, float]:
    """The smallest path depth ``d`` (doubling from ``start``) at which the image of ``sensor``
    has converged: the energy that depths ``d+1 .. 2d`` add is below ``tolerance`` of the total,
    as a photograph has all bounces. Renders at depths d and 2d share their first d bounces (same
    seed), so the difference is the tail itself, with little noise. Returns ``(d, missing)``: the
    depth and the fraction of energy still missing there (measured against 2d); ``(cap, ...)``
    when it never converges below ``cap``."""
    energy = {}

    def total(depth: int) -> float:
        if depth not in energy:
            energy[depth] = float(render(problem, spp=spp, seed=seed, sensor=sensor, max_depth=depth).sum())
        return energy[depth]

    depth = start
    while True:
        deeper = min(2 * depth, cap)
        missing = (total(deeper) - total(depth)) / max(total(deeper), 1e-30)
        if missing < tolerance or deeper == depth:
            return depth, missing
        if deeper == cap:
            return cap, (total(cap) - total(depth)) / max(total(cap), 1e-30)
        depth = deeper

"""Update rules of the scene parameters, one interface (:mod:`.base`): Adam, Gauss-Newton and
Levenberg-Marquardt. :func:`make_optimizer` builds the one a job names."""

from __future__ import annotations

from services.solver.optimize.optimizers.adam import Adam
from services.solver.optimize.optimizers.base import ParameterOptimizer
from services.solver.optimize.optimizers.curvature import Curvature
from services.solver.optimize.optimizers.gauss_newton import GaussNewton, gauss_newton_hessian, gauss_newton_step
from services.solver.optimize.optimizers.levenberg_marquardt import LevenbergMarquardt

OPTIMIZERS = (Adam.name, LevenbergMarquardt.name, GaussNewton.name)


def make_optimizer(name: str, size: int, *, lr: float, betas: tuple[float, float], damping: float,
                   trust_growth: float = 1.5, trust_start: float = 1.0, curvature: str = "successive",
                   curvature_every: int = 1, views: int = 1) -> ParameterOptimizer:
    """The optimizer ``name`` for ``size`` scalars (``lr``: the initial learning rate;
    ``trust_growth``, ``trust_start``: Levenberg-Marquardt's growth of the trust radius and its
    first value in learning rates; ``curvature``, ``curvature_every``: the kind of the
    second-order steps' curvature and how often it is measured, over the job's ``views``)."""
    if name == Adam.name:
        return Adam(size, lr, *betas)
    if name == LevenbergMarquardt.name:
        return LevenbergMarquardt(size, lr, damping, trust_growth, trust_start,
                                  curvature=Curvature(curvature, curvature_every, views))  # type: ignore[arg-type]
    if name == GaussNewton.name:
        return GaussNewton(damping, curvature=Curvature(curvature, curvature_every, views))  # type: ignore[arg-type]
    raise ValueError(f"unknown optimizer {name!r}; known: {', '.join(OPTIMIZERS)}")


__all__ = ["OPTIMIZERS", "Adam", "Curvature", "GaussNewton", "LevenbergMarquardt", "ParameterOptimizer",
           "gauss_newton_hessian", "gauss_newton_step", "make_optimizer"]

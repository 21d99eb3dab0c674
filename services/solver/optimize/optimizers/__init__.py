"""Update rules of the scene parameters, one interface (:mod:`.base`): Adam, Gauss-Newton and
Levenberg-Marquardt. :func:`make_optimizer` builds the one a job names."""

from __future__ import annotations

from services.solver.optimize.optimizers.adam import Adam
from services.solver.optimize.optimizers.base import ParameterOptimizer
from services.solver.optimize.optimizers.gauss_newton import GaussNewton, gauss_newton_hessian, gauss_newton_step
from services.solver.optimize.optimizers.levenberg_marquardt import LevenbergMarquardt

OPTIMIZERS = (Adam.name, LevenbergMarquardt.name, GaussNewton.name)


def make_optimizer(name: str, size: int, *, lr: float, betas: tuple[float, float], damping: float,
                   trust_growth: float = 1.5, trust_start: float = 1.0) -> ParameterOptimizer:
    """The optimizer ``name`` for ``size`` scalars (``lr``: the initial learning rate;
    ``trust_growth``, ``trust_start``: Levenberg-Marquardt's growth of the trust radius and its
    first value in learning rates, the recipe's)."""
    if name == Adam.name:
        return Adam(size, lr, *betas)
    if name == LevenbergMarquardt.name:
        return LevenbergMarquardt(size, lr, damping, trust_growth, trust_start)
    if name == GaussNewton.name:
        return GaussNewton(damping)
    raise ValueError(f"unknown optimizer {name!r}; known: {', '.join(OPTIMIZERS)}")


__all__ = ["OPTIMIZERS", "Adam", "GaussNewton", "LevenbergMarquardt", "ParameterOptimizer", "gauss_newton_hessian",
           "gauss_newton_step", "make_optimizer"]

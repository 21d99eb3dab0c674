"""The interface of an update rule of the scene parameters, documented once.

An optimizer turns one iteration's gradient ``∇z = dz/dp`` ``(P,)`` (Eq. 10), and for the
second-order rules the Gauss-Newton curvature ``H`` ``(P, P)``, into the next parameters,
projected onto their bounds. Each subclass states its update rule in its docstring.

``curvature``         the second-order rules' :class:`~.curvature.Curvature` (None for Adam):
                      :meth:`jacobians_wanted` says which views' Jacobians ``J = dI/dp`` an
                      iteration measures, and :meth:`step` takes them (block-averaged, ``(P, n)``)
                      and updates ``H`` before stepping
``noise_dominated``   whether the recent steps look like noise rather than progress (second-order
                      steps that keep reversing): ``views_per_iteration: "auto"`` then doubles
                      the batch
``state_dict``        everything a resumed run needs (kept in the checkpoint)

A non-finite gradient or curvature is refused with :class:`FloatingPointError`: the loop reports
it as the job's failure instead of writing NaN parameters.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import TYPE_CHECKING, ClassVar

import numpy as np

if TYPE_CHECKING:
    from services.solver.optimize.optimizers.curvature import Curvature


class ParameterOptimizer(ABC):
    """Base class of the update rules (see the module docstring for the interface)."""

    name: ClassVar[str]
    needs_curvature: ClassVar[bool] = False
    curvature: Curvature | None = None
    #: per scalar, one unit of the steps in the scalar's own units ``(P,)`` (None: all 1): Adam's
    #: step and Levenberg-Marquardt's trust radius are measured in it (the recipe's ``step_units``)
    units: np.ndarray | None = None

    def jacobians_wanted(self, k: int, views: list[int]) -> tuple[list[int], int]:
        """The views of iteration ``k``'s batch whose Jacobian the step needs, and how many
        independent estimates of each (none for a first-order rule)."""
        return ([], 0) if self.curvature is None else self.curvature.wanted(k, views)

    @abstractmethod
    def step(self, p: np.ndarray, gradient: np.ndarray, lower: np.ndarray, upper: np.ndarray, *, lr: float,
             hessian: np.ndarray | None = None,
             jacobians: dict[int, list[np.ndarray]] | None = None) -> np.ndarray:
        """The next parameters ``(P,)``, within ``[lower, upper]``; ``lr`` is this iteration's
        learning rate (the job's schedule). A second-order rule takes ``hessian`` as given, or
        updates its curvature from ``jacobians`` (``{view: [J (P, n), ...]}``, as
        :meth:`jacobians_wanted` asked) first."""

    def hessian(self, p: np.ndarray, lr: float, hessian: np.ndarray | None,
                jacobians: dict[int, list[np.ndarray]] | None) -> np.ndarray:
        """A second-order step's ``H``: the one given, or the curvature updated by ``jacobians``."""
        if hessian is not None:
            return hessian
        if self.curvature is None:
            raise ValueError(f"{self.name} needs the curvature H of the iteration")
        return self.curvature.update(jacobians or {}, np.asarray(p, np.float64), lr)

    def noise_dominated(self) -> bool:
        return False

    def refused(self) -> None:
        """The step just returned was refused (not written: :meth:`ParameterSet.refuse
        <services.solver.scene.params.ParameterSet.refuse>`); a rule with a step length shortens it."""
        return None

    def describe(self) -> dict:
        """What the plan and the records show of the optimizer's own state."""
        return {}

    @abstractmethod
    def state_dict(self) -> dict:
        """Plain data (lists, floats) for the checkpoint."""

    @abstractmethod
    def load_state_dict(self, state: dict) -> None:
        """Restore :meth:`state_dict`'s data."""


def check_finite(gradient: np.ndarray, hessian: np.ndarray | None = None) -> None:
    """Raise :class:`FloatingPointError` if the gradient or the curvature is not finite."""
    if not np.all(np.isfinite(gradient)):
        raise FloatingPointError(f"non-finite parameter gradient {np.asarray(gradient).tolist()}")
    if hessian is not None and not np.all(np.isfinite(hessian)):
        raise FloatingPointError("non-finite Gauss-Newton curvature")

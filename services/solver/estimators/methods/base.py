"""The interface of a gradient method, documented once.

A method estimates ``dy/dp`` of Eq. 10 for one sensor. It has two primitives, as Mitsuba's AD
integrators have a backward and a forward mode:

``loss_gradient(dz_dy)``  ``dz/dp = Σ_pixels dz/dy · dy/dp`` (Eq. 10), ``(P,)`` float64, the
                          gradient of every iteration. ``prb`` runs one adjoint pass whatever ``P``;
                          the camera-hit methods contract each camera ray's derivative with ``dz/dy``
                          at its pixel, without forming per-scalar images (the forward mode of their
                          one estimate, :mod:`.camera_hit`; its backward mode for a texture). The
                          default contracts ``gradient_images``.
``gradient_images()``     per-scalar gradient images ``dI/dp``, ``(P, H, W, 3)`` float32 (Eq. 3): the
                          Jacobian of second-order steps, what the loop writes on its images
                          schedule (:mod:`services.solver.optimize.images`) and what ``ndrf
                          gradient`` writes (:mod:`services.solver.optimize.evaluate`).

``candidate_and_gradient`` and ``candidate_gradient_and_images`` are what the loop calls
(:mod:`services.solver.optimize.estimate`): Sec. 5 steps 2-5 for one view, without and with the
Jacobian, built on the two primitives. Every method that traces paths takes the
job's :class:`~services.solver.estimators.render.PathDepth` (there is no default depth).

A method class declares its public ``name`` (a :class:`schemas.methods.Method`), the fields it can
use (``uses``), and how it is built from chosen effects (:meth:`GradientMethod.from_effects`): the
effects may have dropped a field the scene does not need, and the instance then says which fields it
``needs``. A method called without a field it needs raises instead of returning a silently wrong
gradient.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import TYPE_CHECKING, ClassVar

import numpy as np

from schemas.methods import Method

if TYPE_CHECKING:
    from services.solver.estimators.problem import Problem
    from services.solver.estimators.render import PathDepth
    from services.solver.fields.field import NeuralField
    from services.solver.fields.head import ParameterHead
    from services.solver.scene.effects import Effects

RADIANCE, DIFFERENTIAL = "radiance", "differential"

#: ``loss(y) -> (z, dz/dy)`` for a candidate ``y`` of one sensor (``services.solver.estimators.losses``).
Loss = Callable[[np.ndarray], tuple[float, np.ndarray]]


class Fields:
    """The trained fields a method may use (``None`` when not trained)."""

    def __init__(self, radiance: NeuralField | None = None, differential: NeuralField | None = None,
                 head: ParameterHead | None = None):
        self.radiance = radiance
        self.differential = differential
        #: dL_theta as the many-parameter head (``training.head``), instead of ``differential``
        self.head = head


class GradientMethod(ABC):
    """Base class of the gradient methods (see the module docstring for the interface)."""

    name: ClassVar[Method]
    uses: ClassVar[frozenset[str]] = frozenset()
    #: Why the method cannot differentiate a geometry parameter (a pose: moving silhouettes), or
    #: None when it can (the projective integrators, :mod:`.projective`).
    geometry_refusal: ClassVar[str | None] = (
        "it has no boundary term for moving silhouettes: the derivative of a moving edge's visibility is lost")

    def __init__(self, *, radiance: bool = False, differential: bool = False):
        if radiance and RADIANCE not in self.uses or differential and DIFFERENTIAL not in self.uses:
            raise ValueError(f"{self.name} cannot use the fields asked for (it uses {sorted(self.uses) or 'none'})")
        self.needs_radiance = radiance
        self.needs_differential = differential

    @classmethod
    def from_effects(cls, effects: Effects | None, depth: PathDepth | None) -> GradientMethod:
        """The method as the effects shape it (default: every field it can use); ``depth`` is the path
        depth of the methods that trace paths."""
        return cls(radiance=RADIANCE in cls.uses, differential=DIFFERENTIAL in cls.uses)

    def check(self, fields: Fields) -> None:
        if self.needs_radiance and fields.radiance is None:
            raise ValueError(f"{self.name} needs a trained radiance field L_phi")
        if self.needs_differential and fields.differential is None:
            raise ValueError(f"{self.name} needs a trained differential field dL_theta")

    @abstractmethod
    def gradient_images(self, problem: Problem, fields: Fields, *, spp: int, seed: int, sensor: int = 0) -> np.ndarray:
        """Gradient images ``dI/dp``, ``(P, H, W, 3)`` float32."""

    def loss_gradient(self, problem: Problem, fields: Fields, dz_dy: np.ndarray, *, spp: int, seed: int,
                      sensor: int = 0) -> np.ndarray:
        """``dz/dp``, ``(P,)`` float64, for ``dz/dy`` of shape ``(H, W, 3)``. The default contracts
        :meth:`gradient_images`; subclasses override it with something cheaper."""
        return contract(self.gradient_images(problem, fields, spp=spp, seed=seed, sensor=sensor), dz_dy)

    def candidate_and_gradient(self, problem: Problem, fields: Fields, loss: Loss, *, spp: int, gradient_spp: int,
                               seed: int, depth: PathDepth, sensor: int = 0) -> tuple[np.ndarray, float, np.ndarray]:
        """Sec. 5 steps 2-5 for one sensor: the candidate ``y`` ``(H, W, 3)``, ``z(y)`` and ``dz/dp``
        ``(P,)``. ``loss(y) -> (z, dz/dy)``. The default path-traces ``y`` (``spp``, ``depth``)
        with its own samples, then calls :meth:`loss_gradient` (``gradient_spp``, independent
        samples: the estimate of ``dz/dp`` is unbiased for ``l2``)."""
        from services.solver.estimators.render import render
        from services.solver.seeds import derive_seed

        candidate = render(problem, spp=spp, seed=derive_seed(seed, "candidate"), sensor=sensor, depth=depth)
        z, dz_dy = loss(candidate)
        return candidate, z, self.loss_gradient(problem, fields, dz_dy, spp=gradient_spp,
                                                seed=derive_seed(seed, "gradient"), sensor=sensor)

    def candidate_gradient_and_images(self, problem: Problem, fields: Fields, loss: Loss, *, spp: int,
                                      gradient_spp: int, seed: int, depth: PathDepth,
                                      sensor: int = 0) -> tuple[np.ndarray, float, np.ndarray, np.ndarray]:
        """:meth:`candidate_and_gradient` plus the Jacobian ``dI/dp`` ``(P, H, W, 3)`` of the same
        view (what a second-order step needs). The default adds :meth:`gradient_images` with the gradient's
        own seed (the camera-hit methods then query the very rays ``dz/dp`` came from)."""
        from services.solver.seeds import derive_seed

        candidate, z, dz_dp = self.candidate_and_gradient(problem, fields, loss, spp=spp, gradient_spp=gradient_spp,
                                                          seed=seed, depth=depth, sensor=sensor)
        images = self.gradient_images(problem, fields, spp=gradient_spp, seed=derive_seed(seed, "gradient"), sensor=sensor)
        return candidate, z, dz_dp, images


def contract(images: np.ndarray, dz_dy: np.ndarray) -> np.ndarray:
    """``(P, H, W, 3) x (H, W, 3) -> (P,)`` in float64 (Eq. 10)."""
    if images.shape[1:] != dz_dy.shape:
        raise ValueError(f"gradient images {images.shape[1:]} and dz/dy {dz_dy.shape} differ in shape")
    return np.einsum("phwc,hwc->p", images.astype(np.float64), dz_dy.astype(np.float64))

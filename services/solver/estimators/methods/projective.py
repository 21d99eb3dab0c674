"""``prb-projective`` and ``direct-projective``: Mitsuba's projective-sampling integrators (Zhang et
al. 2023, "Projective Sampling for Differentiable Rendering of Geometry"), the methods for geometry.

A render's derivative with respect to a shape's position has two parts: the *interior* term, the
derivative of the shading at fixed visibility (what ``prb`` and every camera-hit method compute),
and the *boundary* term, the light that appears or vanishes as a silhouette or a shadow edge moves.
The boundary term is an integral over the visibility discontinuities; these integrators sample it
by projecting paths onto the silhouettes of the scene's shapes (``sppp`` primary, ``sppi``
indirect samples) and add it to the interior term (``sppc``); each defaults to the render's spp.

``prb-projective``    every bounce (Path Replay Backpropagation with the boundary terms): the job's
                      :class:`~services.solver.estimators.render.PathDepth`
``direct-projective`` direct illumination only (emitters seen directly and one bounce): exact
                      where the scene's light takes no second bounce, else biased (``auto``
                      chooses it only where the light of longer paths is negligible)

Guiding. Mitsuba builds a guide for the indirect boundary samples before every render (an octree
of up to 2^24 leaves by default); it lowers their variance and changes nothing of the
expectation. Building it took 22-31 s per forward-mode render of ``pose-block`` at 16x16 on this
project's 2-core machine (under load), against 1.0-1.1 s without it (``guiding: none``, uniform
samples), so the methods render without a guide (:data:`GUIDING`); Mitsuba's tutorial loop, in
``bench.geometry``, keeps the default.

Forward mode. The tangents are set on the parameters' leaves and carried by the render's own
``dr.forward_to`` through the vertices into the integrator: pushed to the vertices before the
render (what ``prb`` does for a texture's padded copy, :func:`~.prb.push_tangents`), the boundary
term lost most of its derivative (the Jacobian of a translation projected on finite differences:
0.15 and of a rotation 0.07, ``tests/unit/test_geometry.py``, against about 1 carried by the
render).

The interface is :class:`~services.solver.estimators.methods.prb.Prb`'s, and so is the Jacobian:
forward-mode renders, one per group of scalars that change distinct RGB channels (a pose's
scalars change every channel: one render each). The renders are traced at every call (not
frozen): the integrators build their silhouette-sampling guide in Python at each render.
"""

from __future__ import annotations

from typing import ClassVar

from schemas.methods import Method
from services.solver.backend import use_mitsuba
from services.solver.estimators.methods.prb import Prb
from services.solver.estimators.render import PathDepth

#: The guide of the indirect boundary samples (module docstring).
GUIDING = "none"


class PrbProjective(Prb):
    """``prb`` with the boundary terms of moving silhouettes (module docstring)."""

    name = Method.PRB_PROJECTIVE
    integrator_type = "prb_projective"
    pushes_tangents = False
    geometry_refusal: ClassVar[str | None] = None

    def __init__(self, *, depth: PathDepth, radiance: bool = False, differential: bool = False, freeze: bool = False):
        super().__init__(depth=depth, radiance=radiance, differential=differential, freeze=False)
        self.integrator = use_mitsuba().load_dict({"type": self.integrator_type, **depth.integrator_props(),
                                                   "guiding": GUIDING})

    @property
    def freeze(self) -> bool:
        """Never: Mitsuba 3.9 refuses projective integrators inside frozen functions."""
        return False

    @freeze.setter
    def freeze(self, value: bool) -> None:
        """The job's ``render.freeze`` does not apply (:attr:`freeze`)."""


class DirectProjective(PrbProjective):
    """Direct illumination with the boundary terms of moving silhouettes and shadows (module
    docstring); the job's path depth does not apply (it stops after one bounce)."""

    name = Method.DIRECT_PROJECTIVE
    integrator_type = "direct_projective"

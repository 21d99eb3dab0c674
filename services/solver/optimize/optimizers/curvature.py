"""The Gauss-Newton curvature ``H`` of the loss summed over every view, kept by the second-order
optimizers (:mod:`.levenberg_marquardt`, :mod:`.gauss_newton`) from the Jacobians ``J = dI/dp``
of the iteration's views.

For the ``l2`` loss ``z_s = (1/n) Σ (y - t)²`` of view ``s``, ``H_s = (2/n) J_sᵀJ_s``
(:func:`.gauss_newton.hessian_of`, ``J`` averaged over ``BLOCK x BLOCK`` pixel blocks for
``prb``: the noise term of a 1-spp ``J`` falls ``BLOCK²``-fold) and ``H = Σ_s H_s`` over the ``S``
views, estimated from the views that have one as ``(S / #views) Σ H_s``. The three kinds
(``hessian`` of the job):

``successive``  each view's two most recent Jacobians *before* this iteration, cross-multiplied
                (``(1/n)(J_aᵀJ_b + J_bᵀJ_a)``): independent of this iteration's gradient (which the
                Jacobian's noise would otherwise correlate with the curvature, biasing the fixed
                point of ``H⁻¹ g``) and of each other's noise, so unbiased where ``J`` changes
                slowly. Only Jacobians taken within :data:`FRESH` learning rates of the current
                parameters count: while the parameters travel (far from the answer, where the
                signal beats the noise) the curvature comes from this iteration's own Jacobians.
                One view per measurement, turning through the batch's views (a batch of every view
                lists them in one order: its first alone, view 0, had stood for all of them).
``product``     ``(2/n) JᵀJ`` of this iteration's views, biased upwards by ``J``'s variance
``cross``       this iteration's ``J_a`` against a second, independent estimate ``J_b``

The curvature is measured every ``every`` iterations (the job's ``jacobian_every``) and kept in
between. Its state (the curvature and each view's remembered Jacobians) is what a checkpoint
keeps of it.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

#: Pixel blocks averaged before ``JᵀJ`` (module docstring): the noise term of a 1-spp ``J`` falls 16x.
BLOCK = 4


def jacobian_matrix(images: np.ndarray, block: int = 1) -> np.ndarray:
    """``(P, H, W, C)`` -> ``(P, n)`` float64 with ``block x block`` pixel blocks averaged (the
    rows and columns beyond a multiple of ``block`` are dropped)."""
    if images.ndim != 4:
        raise ValueError(f"gradient images must be (P, H, W, C), got shape {images.shape}")
    if block < 1:
        raise ValueError(f"block must be >= 1, got {block}")
    p, h, w, c = images.shape
    if block <= 1 or h < block or w < block:
        return images.reshape(p, -1).astype(np.float64)
    hb, wb = h // block, w // block
    cropped = images[:, :hb * block, :wb * block].astype(np.float64)
    return cropped.reshape(p, hb, block, wb, block, c).mean((2, 4)).reshape(p, -1)


def hessian_of(jac: np.ndarray, other: np.ndarray | None = None) -> np.ndarray:
    """``(2/n) JᵀJ`` of a ``(P, n)`` Jacobian matrix, or with ``other`` (an independent estimate of
    it) the cross product ``(1/n) (J_aᵀJ_b + J_bᵀJ_a)``. Returns ``(P, P)`` float64."""
    if other is None:
        return 2.0 / jac.shape[1] * (jac @ jac.T)
    if other.shape != jac.shape:
        raise ValueError(f"the two Jacobian estimates differ in shape: {jac.shape} and {other.shape}")
    cross = jac @ other.T
    return (cross + cross.T) / jac.shape[1]


def gauss_newton_hessian(images: np.ndarray, other: np.ndarray | None = None, *, block: int = 1) -> np.ndarray:
    """``(2/n) JᵀJ`` for gradient images ``J`` of shape ``(P, H, W, C)`` averaged over ``block``
    pixel blocks; with ``other``, an independent estimate of the same ``J``, the unbiased cross
    product ``(1/n) (J_aᵀJ_b + J_bᵀJ_a)`` (module docstring). Returns ``(P, P)`` float64."""
    if other is not None and other.shape != images.shape:
        raise ValueError(f"the two Jacobian estimates differ in shape: {images.shape} and {other.shape}")
    return hessian_of(jacobian_matrix(images, block), None if other is None else jacobian_matrix(other, block))


#: A remembered Jacobian counts for the ``successive`` curvature while the parameters are within
#: this many learning rates of where it was taken.
FRESH = 2.0

Kind = Literal["successive", "product", "cross"]


class Curvature:
    """The curvature ``H`` ``(P, P)`` of a run (module docstring)."""

    def __init__(self, kind: Kind, every: int = 1, views: int = 1):
        if kind not in ("successive", "product", "cross"):
            raise ValueError(f"unknown curvature kind {kind!r}; known: successive, product, cross")
        if every < 1:
            raise ValueError(f"the curvature is measured every >= 1 iterations, got {every}")
        if views < 1:
            raise ValueError(f"the loss sums over >= 1 views, got {views}")
        self.kind, self.every, self.views = kind, every, views
        self.hessian: np.ndarray | None = None
        #: each view's last two block-averaged Jacobians ``(P, n)``, with the parameters they were taken at
        self.memory: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}

    def state_dict(self) -> dict:
        return {"hessian": None if self.hessian is None else self.hessian.copy(),
                "memory": {str(view): [(taken.copy(), jac.copy()) for taken, jac in pairs]
                           for view, pairs in self.memory.items()}}

    def load_state_dict(self, state: dict) -> None:
        self.hessian = None if state.get("hessian") is None else np.asarray(state["hessian"], np.float64)
        self.memory = {int(view): [(np.asarray(taken, np.float64), np.asarray(jac, np.float64)) for taken, jac in pairs]
                       for view, pairs in (state.get("memory") or {}).items()}

    def wanted(self, k: int, views: list[int]) -> tuple[list[int], int]:
        """The views whose Jacobian iteration ``k`` measures, and how many independent estimates
        of each (2 for ``cross``): none between measurements."""
        if self.hessian is not None and k % self.every:
            return [], 0
        if self.kind != "successive":
            return list(views), 2 if self.kind == "cross" else 1
        # one view, turning through the batch from one measurement to the next: a batch of every
        # view lists them in the same order each time, and its first alone would stand for them all
        return [views[(k // self.every) % len(views)]], 1

    def update(self, jacobians: dict[int, list[np.ndarray]], at: np.ndarray, lr: float) -> np.ndarray:
        """The curvature from this iteration's block-averaged Jacobians ``{view: [J (P, n), ...]}``
        (as many estimates as :meth:`wanted` asked for) at parameters ``at`` ``(P,)``, scaled to
        all the job's views; kept until the next measurement. Returns ``H``."""
        views = self.views
        if not jacobians:
            if self.hessian is None:
                raise ValueError("the first curvature needs at least one measured Jacobian")
            return self.hessian
        if self.kind == "cross":
            total = sum(hessian_of(pair[0], pair[1]) for pair in jacobians.values())
            self.hessian = np.asarray(total) * views / len(jacobians)
            return self.hessian
        current = {view: estimates[0] for view, estimates in jacobians.items()}
        fresh = ([[jac for taken, jac in pairs if np.max(np.abs(taken - at)) <= FRESH * lr]
                  for pairs in self.memory.values()] if self.kind == "successive" else [])
        # views with two fresh Jacobians: their cross product is unbiased by J's noise, where one
        # Jacobian's square is not (mixed in, the product's bias was in every estimate)
        remembered = [hessian_of(*jacs[:2]) for jacs in fresh if len(jacs) >= 2]
        if remembered:
            self.hessian = np.sum(remembered, axis=0) * views / len(remembered)
        else:  # "product", or nothing fresh to remember
            self.hessian = np.sum([hessian_of(jac) for jac in current.values()], axis=0) * views / len(current)
        if self.kind == "successive":
            for view, jac in current.items():
                self.memory[view] = [(np.array(at, np.float64), jac)] + self.memory.get(view, [])[:1]
        return self.hessian

"""Image losses ``z(y)`` and their pixel gradients ``dz/dy`` (paper Sec. 5, steps 2-3)."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np


def image_loss(kind: str, image: np.ndarray, target: np.ndarray) -> tuple[float, np.ndarray]:
    """``(z, dz/dy)`` for ``image`` and ``target`` of shape ``(H, W, 3)``.

    ``l2``: ``z = mean((y - t)²)``, ``dz/dy = 2 (y - t) / n``;
    ``l1``: ``z = mean(|y - t|)``,  ``dz/dy = sign(y - t) / n``.
    """
    if image.shape != target.shape:
        raise ValueError(f"image {image.shape} and target {target.shape} differ in shape")
    diff = image.astype(np.float64) - target.astype(np.float64)
    n = diff.size
    if kind == "l2":
        return float(np.mean(diff ** 2)), (2.0 * diff / n).astype(np.float32)
    if kind == "l1":
        return float(np.mean(np.abs(diff))), (np.sign(diff) / n).astype(np.float32)
    raise ValueError(f"unknown loss {kind!r}; known: l2, l1")


class ImageLoss:
    """The loss of one view against its ``(H, W, 3)`` target, on the host (``loss(y) -> (z,
    dz/dy)`` with numpy, :func:`image_loss`) or on the device (:meth:`device`, Dr.Jit): a method
    that renders with Dr.Jit (``prb``) keeps the image there and reads back only ``z`` and
    ``dz/dp``, one synchronisation per iteration instead of two. Non-finite candidate pixels are
    zeroed on either side and counted through ``sanitized(where, count)``."""

    WHERE = "candidate pixels (non-finite)"

    def __init__(self, kind: str, target: np.ndarray, sanitized: Callable[[str, int], None] = lambda w, c: None):
        if kind not in ("l2", "l1"):
            raise ValueError(f"unknown loss {kind!r}; known: l2, l1")
        self.kind, self.target, self.sanitized = kind, np.asarray(target, np.float32), sanitized
        self._device_target: Any = None  # mi.TensorXf, made on first use

    def __call__(self, image: np.ndarray) -> tuple[float, np.ndarray]:
        bad = ~np.isfinite(image)
        if bad.any():
            self.sanitized(self.WHERE, int(bad.sum()))
            image = np.where(bad, 0.0, image).astype(image.dtype)
        return image_loss(self.kind, image, self.target)

    def image(self, image: np.ndarray) -> np.ndarray:
        """The image the loss compares (this one: ``image`` itself; :class:`BlurredLoss`: ``G image``)."""
        return image

    def jacobian(self, images: np.ndarray) -> np.ndarray:
        """The Jacobian of :meth:`image` for gradient images ``J`` ``(P, H, W, C)``: ``J`` itself."""
        return images

    def device(self, image):
        """``(z, dz/dy, non_finite)`` for a Dr.Jit ``(H, W, 3)`` image: unevaluated Dr.Jit values,
        ``dz/dy`` detached (the weights of the adjoint pass, Eq. 10)."""
        return device_loss(self.kind, image, self.device_target)

    @property
    def device_target(self):
        """The target as a Dr.Jit ``TensorXf`` ``(H, W, 3)``, made on first use."""
        import mitsuba as mi

        if self._device_target is None:
            self._device_target = mi.TensorXf(self.target)
        return self._device_target


def device_loss(kind: str, image, target):
    """:func:`image_loss` in Dr.Jit: ``(z, dz/dy, non_finite)`` for the ``(H, W, 3)`` tensors
    ``image`` and ``target``, unevaluated; ``dz/dy`` is detached and non-finite pixels of ``image``
    count as 0 (their number is ``non_finite``). Pure Dr.Jit, so it may run inside a frozen
    function (:mod:`services.solver.estimators.methods.prb`)."""
    import drjit as dr

    y = dr.detach(image)
    finite = dr.isfinite(y)
    diff = dr.select(finite, y, 0.0) - target
    n = float(math.prod(target.shape))
    if kind == "l2":
        return dr.sum(dr.square(diff), axis=None) / n, diff * (2.0 / n), dr.count(~finite, axis=None)
    return dr.sum(dr.abs(diff), axis=None) / n, dr.sign(diff) / n, dr.count(~finite, axis=None)


def gaussian_matrix(size: int, sigma: float) -> np.ndarray:
    """The ``(size, size)`` float64 matrix of a 1-D Gaussian blur of standard deviation ``sigma``
    pixels, zero outside the image and truncated at 3 ``sigma``: symmetric, so it is its own
    adjoint (``Gᵀ = G``). ``sigma == 0`` gives the identity."""
    if not sigma >= 0:
        raise ValueError(f"the blur's sigma must be >= 0 pixels, got {sigma}")
    if sigma == 0:
        return np.eye(size)
    offsets = np.arange(size)[:, None] - np.arange(size)[None, :]
    kernel = np.exp(-0.5 * (offsets / sigma) ** 2) * (np.abs(offsets) <= 3 * sigma)
    return kernel / kernel.sum(axis=1, keepdims=True).max()   # every row of the interior sums to 1


def blur(images: np.ndarray, sigma: float) -> np.ndarray:
    """``G images``: the separable Gaussian blur of images ``(..., H, W, C)`` (:func:`gaussian_matrix`
    on each axis), float64."""
    if sigma == 0:
        return np.asarray(images, np.float64)
    h, w = images.shape[-3], images.shape[-2]
    return np.einsum("ij,...jkc,lk->...ilc", gaussian_matrix(h, sigma), np.asarray(images, np.float64),
                     gaussian_matrix(w, sigma), optimize=True)


class BlurredLoss:
    """The loss of one view on images blurred by a Gaussian of ``sigma`` pixels, ``z(G y)`` against
    ``G t`` (coarse to fine: a pose far from its target still overlaps it once both are blurred,
    and the loss's downhill direction then points towards it). On the host only, so a method takes
    its host path (:class:`ImageLoss` alone runs on the device).

    ``l2``: ``z = mean((G(y - t))²)``, ``dz/dy = 2 G G(y - t) / n`` (``G`` symmetric);
    ``l1``: ``z = mean(|G(y - t)|)``, ``dz/dy = G sign(G(y - t)) / n``. The Jacobian of ``G y`` is
    ``G J`` (:meth:`jacobian`), which the curvature must use with this loss."""

    WHERE = ImageLoss.WHERE

    def __init__(self, loss: ImageLoss, sigma: float):
        if not sigma > 0:
            raise ValueError(f"a blurred loss needs sigma > 0 pixels, got {sigma} (use the ImageLoss itself)")
        self.kind, self.sigma, self.sanitized = loss.kind, float(sigma), loss.sanitized
        self.target = blur(loss.target, self.sigma)    # the image it compares against: G t

    def __call__(self, image: np.ndarray) -> tuple[float, np.ndarray]:
        if image.shape != self.target.shape:
            raise ValueError(f"image {image.shape} and target {self.target.shape} differ in shape")
        bad = ~np.isfinite(image)
        if bad.any():
            self.sanitized(self.WHERE, int(bad.sum()))
            image = np.where(bad, 0.0, image)
        diff = blur(image, self.sigma) - self.target
        n = diff.size
        if self.kind == "l2":
            return float(np.mean(diff ** 2)), blur(2.0 * diff / n, self.sigma).astype(np.float32)
        return float(np.mean(np.abs(diff))), blur(np.sign(diff) / n, self.sigma).astype(np.float32)

    def image(self, image: np.ndarray) -> np.ndarray:
        """``G image`` ``(H, W, C)``: the image the loss compares."""
        return blur(image, self.sigma)

    def jacobian(self, images: np.ndarray) -> np.ndarray:
        """``G J`` for gradient images ``J`` ``(P, H, W, C)``."""
        return blur(images, self.sigma)

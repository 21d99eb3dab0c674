"""Image losses ``z(y)`` and their pixel gradients ``dz/dy`` (paper Sec. 5, steps 2-3)."""

from __future__ import annotations

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

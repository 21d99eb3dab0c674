"""Which derivatives are carried, and where: the outputs of ``dL_theta``.

The optimized scalars ``p_1..p_P`` are reduced to the ``A`` *active* ones (`choose_effects` drops
scalars no camera path depends on), and each active scalar carries only the RGB channels it can
change (an RGB albedo component changes one channel: RGB transport never mixes channels). The
``K`` outputs of ``dL_theta`` are the flattened ``(active scalar, channel)`` pairs.

Tensors of derivatives are ``(..., A, 3)``; :meth:`pack` gives ``(..., K)`` and :meth:`unpack`
puts ``(..., K)`` back with zeros in the channels not carried.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch


@dataclass(frozen=True)
class DerivativeLayout:
    scalars: tuple[int, ...]              # indices of the active scalars into ParameterSet.scalars
    channels: tuple[tuple[int, ...], ...]  # RGB channels carried, per active scalar

    @classmethod
    def full(cls, n: int) -> DerivativeLayout:
        return cls(tuple(range(n)), tuple((0, 1, 2) for _ in range(n)))

    @classmethod
    def by_component(cls, sizes: list[int]) -> DerivativeLayout:
        """Every scalar active; component ``c`` of a three-component (RGB) parameter carries channel
        ``c`` alone (RGB transport never mixes channels), any other scalar all three. What the
        probe of `choose_effects` would measure for an RGB value, known without probing (``prb``)."""
        channels = [((c,) if size == 3 else (0, 1, 2)) for size in sizes for c in range(size)]
        return cls(tuple(range(len(channels))), tuple(channels))

    @property
    def active(self) -> int:
        return len(self.scalars)

    @property
    def outputs(self) -> int:
        return sum(len(c) for c in self.channels)

    @functools.cached_property
    def _flat(self) -> torch.Tensor:  # made once: on CUDA each torch.tensor(list) is a copy to the device
        return torch.tensor([a * 3 + c for a, chans in enumerate(self.channels) for c in chans], dtype=torch.long)

    def pack(self, t: torch.Tensor) -> torch.Tensor:
        return t.reshape(*t.shape[:-2], self.active * 3)[..., self._flat]

    def unpack(self, y: torch.Tensor) -> torch.Tensor:
        out = torch.zeros(*y.shape[:-1], self.active * 3, dtype=y.dtype)
        out[..., self._flat] = y
        return out.reshape(*y.shape[:-1], self.active, 3)

    def scatter_images(self, images: np.ndarray, n: int) -> np.ndarray:
        """``(A, H, W, 3)`` gradient images of the active scalars -> ``(n, H, W, 3)`` (zeros elsewhere)."""
        out = np.zeros((n,) + images.shape[1:], dtype=images.dtype)
        out[list(self.scalars)] = images
        return out

"""Field components: encodings of position and direction (PyTorch, CPU friendly)."""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import nn

from schemas.solver import HashGridConfig

# Spatial hash of Teschner et al. as used by instant-ngp; the first prime is 1 (coherent in x).
# Computed in int32 with wrap-around: the table index keeps only the low log2(T) bits, which
# wrapping multiplication preserves, and int32 arithmetic is ~3x faster than int64 on the CPU.
_PRIME_Y = 2654435761 - (1 << 32)  # the same bits as the uint32 prime, as an int32
_PRIME_Z = 805459861


class HashGridEncoding(nn.Module):
    resolution: torch.Tensor  # buffers, declared for the type checker (nn.Module types attributes loosely)
    stride: torch.Tensor
    offset: torch.Tensor
    """Multiresolution hash grid: ``(B, 3)`` positions in ``[0, 1]^3`` -> ``(B, L·F)`` features.

    Level ``l`` has resolution ``floor(base · scale^l)``; a level whose ``(res + 1)^3`` vertices
    fit in the table is indexed densely, the others by the spatial hash. All levels live in one
    table. :meth:`lookup` computes the 8 corner indices and trilinear weights of every level
    (the expensive part, shared by fields with the same encoding config); one ``embedding_bag``
    gathers and blends the corners.
    """

    def __init__(self, config: HashGridConfig):
        super().__init__()
        self.config = config
        table = 1 << config.log2_hashmap_size
        res = [int(math.floor(config.base_resolution * config.per_level_scale ** level))
               for level in range(config.n_levels)]
        if any(b < a for a, b in zip(res, res[1:])):
            raise ValueError("grid resolutions must not decrease with the level")
        self.n_dense = sum((r + 1) ** 3 <= table for r in res)
        sizes = [min(table, (r + 1) ** 3) for r in res]
        offsets = [sum(sizes[:level]) for level in range(len(sizes))]
        self.table_size = table
        self.register_buffer("resolution", torch.tensor(res, dtype=torch.float32), persistent=False)
        self.register_buffer("stride", torch.tensor([r + 1 for r in res[:self.n_dense]], dtype=torch.int32),
                             persistent=False)
        self.register_buffer("offset", torch.tensor(offsets, dtype=torch.int32)[None, :, None], persistent=False)
        self.table = nn.Parameter(torch.empty(sum(sizes), config.features_per_level).uniform_(-1e-4, 1e-4))

    @property
    def output_dim(self) -> int:
        return self.config.output_dim

    def lookup(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Corner indices ``(B, L, 8)`` int32 into the table and trilinear weights ``(B, L, 8)``."""
        batch, levels, nd = x.shape[0], self.config.n_levels, self.n_dense
        pos = x.clamp(0.0, 1.0 - 1e-6)[:, :, None] * self.resolution       # (B, 3, L)
        cell = pos.floor()
        frac = pos - cell
        c = cell.to(torch.int32)

        def pairs(lo, hi):  # (B, L', 2)
            return torch.stack([lo, hi], -1)

        w = [pairs(1.0 - frac[:, axis], frac[:, axis]) for axis in range(3)]
        weight = w[0][:, :, :, None, None] * w[1][:, :, None, :, None] * w[2][:, :, None, None, :]
        weight = weight.reshape(batch, levels, 8)

        parts = []
        if nd:  # dense levels: i = x + s (y + s z)
            s = self.stride
            cx, cy, cz = c[:, 0, :nd], c[:, 1, :nd] * s, c[:, 2, :nd] * s * s
            ax, ay, az = pairs(cx, cx + 1), pairs(cy, cy + s), pairs(cz, cz + s * s)
            parts.append((ax[:, :, :, None, None] + ay[:, :, None, :, None] + az[:, :, None, None, :]).reshape(batch, nd, 8))
        if nd < levels:  # hashed levels
            cx, cy, cz = c[:, 0, nd:], c[:, 1, nd:], c[:, 2, nd:]
            ax = pairs(cx, cx + 1)
            ay = pairs(cy * _PRIME_Y, (cy + 1) * _PRIME_Y)
            az = pairs(cz * _PRIME_Z, (cz + 1) * _PRIME_Z)
            hashed = (ax[:, :, :, None, None] ^ ay[:, :, None, :, None] ^ az[:, :, None, None, :]) & (self.table_size - 1)
            parts.append(hashed.reshape(batch, levels - nd, 8))
        return torch.cat(parts, 1) + self.offset, weight

    def interpolate(self, index: torch.Tensor, weight: torch.Tensor) -> torch.Tensor:
        """Blend the table rows of a :meth:`lookup`: ``(B, L·F)``."""
        return _Blend.apply(self.table, index, weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.interpolate(*self.lookup(x))


class _Blend(torch.autograd.Function):
    """``out[b, l] = Σ_c weight[b, l, c] · table[index[b, l, c]]``: ``(B, L, 8)`` -> ``(B, L·F)``.

    Forward is one ``embedding_bag``. Backward only needs the table's gradient (indices and
    weights are constants of a lookup): one ``index_add_`` of the weighted output gradients, about
    twice as fast on the CPU as ``embedding_bag``'s own backward, which also prepares gradients
    for the per-sample weights."""

    @staticmethod
    def forward(ctx, table, index, weight):
        ctx.save_for_backward(index, weight)
        ctx.rows = table.shape[0]
        out = F.embedding_bag(index.reshape(-1, 8), table, per_sample_weights=weight.reshape(-1, 8), mode="sum")
        return out.reshape(index.shape[0], -1)

    @staticmethod
    def backward(ctx, grad):
        index, weight = ctx.saved_tensors
        batch, levels, _ = index.shape
        rows = grad.reshape(batch, levels, 1, -1) * weight[..., None]            # (B, L, 8, F)
        out = grad.new_zeros(ctx.rows, rows.shape[-1])
        out.index_add_(0, index.reshape(-1).long(), rows.reshape(-1, rows.shape[-1]))
        return out, None, None


class SphericalHarmonicsEncoding(nn.Module):
    """Real spherical harmonics of a unit direction: ``(B, 3)`` -> ``(B, degree²)``."""

    def __init__(self, degree: int):
        super().__init__()
        if not 1 <= degree <= 4:
            raise ValueError(f"spherical harmonics degree must be in [1, 4], got {degree}")
        self.degree = degree

    @property
    def output_dim(self) -> int:
        return self.degree ** 2

    def forward(self, d: torch.Tensor) -> torch.Tensor:
        x, y, z = d.unbind(-1)
        out = [torch.full_like(x, 0.28209479177387814)]
        if self.degree > 1:
            out += [-0.48860251190291987 * y, 0.48860251190291987 * z, -0.48860251190291987 * x]
        if self.degree > 2:
            xx, yy, zz = x * x, y * y, z * z
            out += [1.0925484305920792 * x * y, -1.0925484305920792 * y * z,
                    0.94617469575755997 * zz - 0.31539156525251999, -1.0925484305920792 * x * z,
                    0.54627421529603959 * (xx - yy)]
        if self.degree > 3:
            out += [0.59004358992664352 * y * (yy - 3 * xx), 2.8906114426405538 * x * y * z,
                    0.45704579946446572 * y * (1 - 5 * zz), 0.3731763325901154 * z * (5 * zz - 3),
                    0.45704579946446572 * x * (1 - 5 * zz), 1.4453057213202769 * z * (xx - yy),
                    0.59004358992664352 * x * (3 * yy - xx)]
        return torch.stack(out, -1)

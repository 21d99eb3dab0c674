"""``NeuralField``: position/direction/normal -> radiance-like outputs.

``L_phi``    = ``NeuralField(config, channels=3)``        reflected radiance ``L_r(x, ω_o)`` (RGB)
``dL_theta`` = ``NeuralField(config, channels=K)``        ``∂L_r / ∂p_i`` for the active scalars: ``K``
                                                          outputs, the (scalar, RGB channel) pairs the
                                                          plan carries (one per albedo component)

Positions are normalised to the unit cube by the scene's bounding box with one scale for all
axes (a scene in millimetres and one in metres train identically). Outputs are multiplied by a
per-channel ``output_scale`` fixed before training from the magnitude of the first right-hand
side, so the network itself always learns values of order one: light sources of 1e4 or albedos of
1e-3 do not change the conditioning.
"""

from __future__ import annotations

import torch
from torch import nn

from schemas.solver import FieldConfig
from services.solver.fields.encoding import HashGridEncoding, SphericalHarmonicsEncoding
from services.solver.fields.mlp import make_mlp
from services.solver.fields.query import FieldQuery


class NeuralField(nn.Module):
    center: torch.Tensor  # buffers, declared for the type checker (nn.Module types attributes loosely)
    inv_extent: torch.Tensor
    output_scale: torch.Tensor
    """Query ``(K, 3)`` positions, directions and normals -> ``(K, channels)``."""

    def __init__(self, config: FieldConfig, channels: int, box_min, box_max):
        super().__init__()
        if channels < 1:
            raise ValueError(f"a field needs at least one output channel, got {channels}")
        self.config = config
        self.channels = channels
        lo, hi = torch.as_tensor(box_min, dtype=torch.float32), torch.as_tensor(box_max, dtype=torch.float32)
        extent = float((hi - lo).max().clamp_min(1e-12))
        self.register_buffer("center", (lo + hi) / 2)
        self.register_buffer("inv_extent", torch.tensor(1.0 / extent))
        self.register_buffer("output_scale", torch.ones(channels))
        self.position = HashGridEncoding(config.encoding)
        self.direction = SphericalHarmonicsEncoding(config.direction_sh_degree) if config.direction_sh_degree else None
        in_dim = (self.position.output_dim + (self.direction.output_dim if self.direction else 0)
                  + (3 if config.use_normal else 0))
        self.mlp = make_mlp(in_dim, channels, config.mlp)
        self._lookup_key = ("hashgrid", config.encoding.model_dump_json(), tuple(self.center.tolist()), extent)
        self._inputs_key = ("inputs", config.direction_sh_degree, config.use_normal)

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return (x - self.center) * self.inv_extent + 0.5

    def precompute(self, query: FieldQuery) -> FieldQuery:
        """Compute and memoise in ``query`` everything of an evaluation that depends only on
        where it is (hash-grid corner indices and trilinear weights ``(K, L, 8)``, direction and
        normal features ``(K, D)``): later evaluations at these points, and at any
        :meth:`FieldQuery.select` of them, only gather table rows and run the MLP."""
        if len(query):
            self._lookup(query), self._inputs(query)
        return query

    def _lookup(self, query: FieldQuery):
        return self._cached(query, self._lookup_key, lambda: self.position.lookup(self.normalize(query.x)))

    def _inputs(self, query: FieldQuery) -> torch.Tensor:
        return self._cached(query, self._inputs_key, lambda: torch.cat(
            ([self.direction(query.wo)] if self.direction is not None else [])
            + ([query.n] if self.config.use_normal else []), -1))

    def forward(self, query: FieldQuery) -> torch.Tensor:
        if len(query) == 0:
            return torch.zeros(0, self.channels)
        # Everything but the table rows and the MLP depends only on the query: computed once and
        # shared by the fields that evaluate the same points (L_phi and dL_theta at x').
        features = torch.cat([self.position.interpolate(*self._lookup(query)), self._inputs(query)], -1)
        return self.mlp(features) * self.output_scale

    @staticmethod
    def _cached(query: FieldQuery, key, compute):
        value = query.cache.get(key)
        if value is None:
            with torch.no_grad():
                value = query.cache[key] = compute()
        return value


def evaluate(field: NeuralField, query: FieldQuery, where: torch.Tensor | None = None,
             chunk: int = 1 << 16) -> torch.Tensor:
    """Evaluate ``field`` on the lanes ``where`` (bool ``(K,)``; all when None), zeros elsewhere.

    Runs in chunks so that memory stays bounded for large camera passes; respects the caller's
    grad mode.
    """
    out = torch.zeros(len(query), field.channels)
    index = torch.arange(len(query)) if where is None else torch.nonzero(where).squeeze(1)
    if index.numel() <= chunk:
        out[index] = field(query.select(index))
        return out
    for start in range(0, index.numel(), chunk):
        part = index[start:start + chunk]
        out[part] = field(query.select(part))
    return out

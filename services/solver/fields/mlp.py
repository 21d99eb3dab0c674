"""The fully connected network of a field."""

from __future__ import annotations

from torch import nn

from schemas.solver import MLPConfig


def make_mlp(in_dim: int, out_dim: int, config: MLPConfig) -> nn.Sequential:
    """``in_dim -> [width, ReLU] x layers -> out_dim`` (linear output: derivatives can be negative)."""
    layers: list[nn.Module] = []
    width = in_dim
    for _ in range(config.hidden_layers):
        layers += [nn.Linear(width, config.hidden_width), nn.ReLU(inplace=True)]
        width = config.hidden_width
    layers.append(nn.Linear(width, out_dim))
    return nn.Sequential(*layers)

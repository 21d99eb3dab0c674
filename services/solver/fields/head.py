"""``ParameterHead``: ``dL_theta`` for many parameters (paper Sec. 8), a low-rank factorization.

The differential field of :mod:`.field` has one output per (scalar, RGB channel): its output layer
grows with P, which a texture (P = 768 for 16 x 16 RGB texels) rules out. The head instead learns

    H_k(x, ω) ≈ Σ_r B_r(x, ω) C[r, k]          B: (K, R, 3) basis functions (one network)
                                                C: (R, P) learned coefficients

``H_k`` is only the *indirect* part of ``∂L_r / ∂p_k`` (``services/solver/training/head.py``): the
BSDF's own derivative at a point (a texel's local effect, sharp from one texel to the next) is
computed exactly with Dr.Jit AD, and what is left, ``∫ f ∂L(x')``, is smooth across neighbouring
texels, which is what a rank-R factorization can represent. The alternative of Sec. 8, a
hypernetwork mapping a parameter's embedding to the weights of a per-parameter field, would need a
network evaluation per (point, parameter) pair; with ``C`` the contraction with ``dz/dy`` runs once
over R basis values per camera ray (``Cᵀ v``), whatever P.
"""

from __future__ import annotations

import torch
from torch import nn

from schemas.solver import FieldConfig
from services.solver.fields.field import NeuralField
from services.solver.fields.query import FieldQuery


class ParameterHead(nn.Module):
    """``B(x, ω)`` ``(K, R, 3)`` and ``C`` ``(R, P)``; :meth:`forward` returns ``B`` flattened
    ``(K, 3R)`` (channel-major per basis: ``[r, c] -> 3r + c``) so that chunked evaluation
    (:func:`~services.solver.fields.field.evaluate`) and the weight average work as for any field."""

    def __init__(self, config: FieldConfig, rank: int, scalars: int, box_min, box_max):
        super().__init__()
        if rank < 1 or scalars < 1:
            raise ValueError(f"a head needs a rank and parameters, got rank {rank}, {scalars} parameters")
        self.rank, self.scalars = rank, scalars
        self.basis = NeuralField(config, 3 * rank, box_min, box_max)
        # small coefficients: H starts near zero, as a fresh NeuralField's outputs do
        self.coefficients = nn.Parameter(torch.randn(rank, scalars) / rank)

    @property
    def channels(self) -> int:
        return 3 * self.rank

    @property
    def output_scale(self) -> torch.Tensor:
        """The RGB scale of ``H`` (3,): the scale of the basis' first three outputs."""
        return self.basis.output_scale[:3]

    def calibrate(self, rgb_scale: torch.Tensor) -> None:
        """Scale every basis function's RGB outputs by ``rgb_scale`` ``(3,)`` (the magnitude of the
        first right-hand side): the network learns values of order one."""
        with torch.no_grad():
            self.basis.output_scale.copy_(rgb_scale.repeat(self.rank))

    def precompute(self, query: FieldQuery) -> FieldQuery:
        return self.basis.precompute(query)

    def forward(self, query: FieldQuery) -> torch.Tensor:
        return self.basis(query)

    def values(self, query: FieldQuery) -> torch.Tensor:
        """``B`` at ``query``: ``(K, R, 3)``."""
        return self.basis(query).reshape(-1, self.rank, 3)

    @staticmethod
    def combine(basis: torch.Tensor, coefficients: torch.Tensor) -> torch.Tensor:
        """``H_k = Σ_r B_r C[r, k]``: ``(K, R, 3) x (R, S) -> (K, S, 3)``."""
        return torch.einsum("krc,rs->ksc", basis, coefficients)

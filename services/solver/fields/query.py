"""Where a field is evaluated (plain torch tensors, no Dr.Jit)."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class FieldQuery:
    """Where to evaluate a field: world position ``x``, world outgoing direction ``ω_o`` (pointing
    away from the surface, towards the previous vertex) and geometric normal ``n``; ``(K, 3)`` each."""

    x: torch.Tensor
    wo: torch.Tensor
    n: torch.Tensor
    #: per-query memo of encoding lookups, shared by fields with the same encoding (see NeuralField)
    cache: dict = field(default_factory=dict, repr=False, compare=False)

    def __len__(self) -> int:
        return self.x.shape[0]

    def compact(self, where: torch.Tensor) -> tuple[torch.Tensor, FieldQuery]:
        """The lane indices where ``where`` (bool ``(K,)``) holds and the query of those lanes."""
        index = torch.nonzero(where).squeeze(1)
        return index, self.select(index)

    def select(self, index: torch.Tensor) -> FieldQuery:
        """The query of the lanes ``index``; precomputed encoding inputs are selected with them
        (a pool computes them once, every batch drawn from it reuses them)."""
        cache = {key: tuple(v[index] for v in value) if isinstance(value, tuple) else value[index]
                 for key, value in self.cache.items()}
        return FieldQuery(self.x[index], self.wo[index], self.n[index], cache)

    def repeat(self, times: int) -> FieldQuery:
        return FieldQuery(self.x.repeat_interleave(times, 0), self.wo.repeat_interleave(times, 0),
                          self.n.repeat_interleave(times, 0))

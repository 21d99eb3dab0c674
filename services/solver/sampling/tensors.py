"""Dr.Jit lanes -> torch tensors: the hand-over point between Mitsuba and the neural fields."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from services.solver.fields.query import FieldQuery
from services.solver.jit_types import Bool, Color, Vector


def rgb(value: Color | Vector) -> torch.Tensor:
    """``(K, 3)`` float32 tensor of a ``mi.Color3f`` / ``mi.Vector3f`` with ``K`` lanes."""
    return torch.from_numpy(np.ascontiguousarray(np.array(value, dtype=np.float32).reshape(3, -1).T))


def mask(value: Bool) -> torch.Tensor:
    """``(K,)`` bool tensor."""
    return torch.from_numpy(np.array(value, dtype=bool).reshape(-1))


def field_query(si: mi.SurfaceInteraction3f) -> FieldQuery:
    """The query of every lane of ``si`` (``si.wi`` is the local outgoing direction)."""
    with dr.suspend_grad():
        wo = si.to_world(si.wi)
        n = mi.Vector3f(si.n)
        dr.eval(si.p, wo, n)
    return FieldQuery(rgb(si.p), rgb(wo), rgb(n))

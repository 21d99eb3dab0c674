"""The residual of the many-parameter head (paper Eq. 6 with Sec. 8's factorization).

Split the derivative of reflected radiance w.r.t. a BSDF scalar ``p_k`` (``∂E = 0``) as
``∂_k L_r = D_k + H_k``:

    D_k(x, ω_o) = ∫ ∂_k f(x) [E(x') + L_r(x')] dω⊥      the parameter's local effect (a texel's own
                                                          footprint: sharp across texels), exact
    H_k(x, ω_o) = ∫ f(x) [D_k(x') + H_k(x')] dω⊥        the indirect part, smooth across texels

The head learns ``H_k ≈ Σ_r B_r C[r, k]`` (``services.solver.fields.head``) from the residual

    r_k(x, ω_o) = B(x)C_k - mean_M[ T · (D̂_k(x') + sg(B(x') C_k)) ]                            (Eq. 6, 9)
    D̂_k(x')     = ∂_k e' + ∂_k T' · sg(L_phi(x''))      one MIS bounce from x' (forward-mode AD)

with ``sg`` the stop-gradient (``L_phi`` is a constant, Sec. 6.1; with ``semi_gradient`` the
right-hand side is). Each step takes ``S`` indices ``k`` drawn among the scalars the batch's
second bounces depend on (one reverse-mode pass finds them): a texel's source ``D̂_k`` is zero
on every lane whose ``x'`` is outside its footprint, and drawing among those that are not keeps
every step informative. The weighting this puts on the texels moves no fixed point (every
``r_k`` is zero there). Shapes: ``N`` points, ``M`` incident samples, ``S`` drawn scalars.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from services.solver.estimators.methods.head import exact_vertex
from services.solver.estimators.problem import Problem
from services.solver.fields.field import NeuralField, evaluate
from services.solver.fields.head import ParameterHead
from services.solver.fields.query import FieldQuery
from services.solver.sampling.camera import make_sampler
from services.solver.sampling.incident import IncidentGeometry, evaluate_attached, evaluate_incident, sample_geometry
from services.solver.sampling.tensors import field_query, mask, rgb, to_device
from services.solver.seeds import derive_seed
from services.solver.training.residuals import draw_geometry


@dataclass
class HeadBatch:
    """One batch of the head's residual (torch).

    points      FieldQuery (N)     x                  weight       (N,)    p_ref / p of Eq. 8
    throughput  (N, M, 3)          T                  scalars      (S,)    the drawn k
    hit_index   (H,) long          lanes with x'      hits         FieldQuery (H): x'
    d_emitted   (H, S, 3)          ∂_k e'             d_throughput (H, S, 3) ∂_k T'
    second_index (H2,) long        lanes of hits whose x'' is a surface; seconds FieldQuery (H2): x''
    """

    points: FieldQuery
    weight: torch.Tensor
    throughput: torch.Tensor
    scalars: torch.Tensor
    hit_index: torch.Tensor
    hits: FieldQuery
    d_emitted: torch.Tensor
    d_throughput: torch.Tensor
    second_index: torch.Tensor
    seconds: FieldQuery
    values: np.ndarray          # the parameters it was drawn at (redrawn when they change)

    @property
    def shape(self) -> tuple[int, int]:
        return self.throughput.shape[0], self.throughput.shape[1]


def _touched(problem: Problem, second: IncidentGeometry, seed: int) -> np.ndarray:
    """Indices of the scalars that the second bounces' BSDF values depend on: one reverse-mode
    pass of a randomly weighted sum of them (``(T,)`` long, possibly empty)."""
    params = problem.parameters
    lanes = dr.width(second.active)
    rng = np.random.default_rng(seed)
    with params.tracking():
        emitted, throughput = evaluate_attached(problem.scene.scene, second, attach_bsdf=True, attach_emission=False)
        with dr.resume_grad():
            u = mi.Color3f(rng.random((3, lanes), dtype=np.float32))
            total = dr.sum(dr.select(dr.isfinite(emitted + throughput), (emitted + throughput) * u, 0.0), axis=None)
            dr.backward(total)
        return np.flatnonzero(params.gradient_vector())


def draw_head_batch(problem: Problem, n: int, m: int, scalars: int, seed: int,
                    camera_fraction: float = 0.0) -> HeadBatch:
    """Sample ``n`` points with ``m`` incident samples (Eq. 8, 9), one more bounce from each
    ``x'``, draw ``scalars`` indices ``k`` and evaluate ``T``, ``∂_k e'`` and ``∂_k T'``."""
    scene = problem.scene.scene
    g = draw_geometry(problem, n, m, seed, camera_fraction)
    first = g.geometry
    inc = evaluate_incident(scene, first, attach_bsdf=True, attach_emission=False)
    problem.count_sanitized("residual", inc.sanitized)
    sampler = make_sampler(derive_seed(seed, "second"), n * m)
    second = sample_geometry(scene, first.hit, sampler, delta_depth=problem.delta_depth, active=inc.hit_surface)
    second.schedule()
    touched = _touched(problem, second, derive_seed(seed, "touched"))
    rng = np.random.default_rng(derive_seed(seed, "scalars"))
    pool = touched if touched.size else np.arange(problem.parameters.n)
    drawn = np.sort(rng.choice(pool, size=min(scalars, pool.size), replace=False))
    d_emitted, d_throughput, _ = exact_vertex(problem, second, [int(i) for i in drawn])
    hits = mask(inc.hit_surface)
    hit_index = torch.nonzero(hits).squeeze(1)
    stacked_e = torch.stack([rgb(d) for d in d_emitted], 1)[hit_index]                 # (H, S, 3)
    stacked_t = torch.stack([rgb(d) for d in d_throughput], 1)[hit_index]
    second_hits = mask(second.hit_surface)[hit_index]
    second_index = torch.nonzero(second_hits).squeeze(1)
    seconds = field_query(second.hit).select(hit_index[second_index])
    return HeadBatch(g.points, g.weight, rgb(inc.throughput).reshape(n, m, 3), to_device(drawn),
                     hit_index, field_query(first.hit).select(hit_index), stacked_e, stacked_t, second_index,
                     seconds, problem.parameters.values())


def source(batch: HeadBatch, radiance: NeuralField | None) -> torch.Tensor:
    """``D̂_k(x')`` on the lanes with ``x'``: ``(H, S, 3)`` (``L_phi`` detached; zero without it)."""
    out = batch.d_emitted
    if radiance is not None and len(batch.second_index):
        with torch.no_grad():
            l2 = torch.zeros(len(batch.hits), 3)
            l2[batch.second_index] = evaluate(radiance, batch.seconds)
        out = out + batch.d_throughput * l2[:, None, :]
    return out


def head_rhs_samples(batch: HeadBatch, head: ParameterHead, radiance: NeuralField | None,
                     indirect: bool = True) -> torch.Tensor:
    """The ``M`` terms of the right-hand side, ``(N, M, S, 3)``: ``T · (D̂_k(x') + B(x') C_k)``
    (``indirect=False``: the source alone, for the output scale)."""
    n, m = batch.shape
    inner = source(batch, radiance)
    if indirect and len(batch.hits):
        inner = inner + head.combine(head.values(batch.hits), head.coefficients[:, batch.scalars])
    out = torch.zeros(n * m, len(batch.scalars), 3)
    out[batch.hit_index] = inner
    return batch.throughput[:, :, None, :] * out.reshape(n, m, len(batch.scalars), 3)


def head_lhs(batch: HeadBatch, head: ParameterHead) -> torch.Tensor:
    """``B(x) C_k``: ``(N, S, 3)``."""
    return head.combine(head.values(batch.points), head.coefficients[:, batch.scalars])

"""``ndrf-rhs`` with the many-parameter head (paper Sec. 8): the gradient of P scalars, textures
included, without P per-scalar outputs and without P images.

At a camera hit ``x`` (delta throughput ``β``, sensor weight ``W``), one MIS bounce to ``x'`` and one
more to ``x''`` (``T``, ``T'``: the throughputs of Eq. 9 at ``x`` and ``x'``, ``e``, ``e'``: their
``emitted`` terms), the derivative of the pixel's radiance w.r.t. scalar ``k`` is estimated as
(Eq. 4 twice, with ``∂L_r = D + H``; ``services.solver.training.head``)

    dI_k = W β [ ∂_k e + ∂_k T · L_phi(x')                      D_k(x): exact (Dr.Jit AD)
                 + T · ( ∂_k e' + ∂_k T' · L_phi(x'')            D_k(x'): exact (Dr.Jit AD)
                         + Σ_r B_r(x') C[r, k] ) ]                H_k(x'): the head

Only BSDF parameters are carried (``∂E = 0``; an emitter parameter is refused when the method is
built). Shapes: ``K`` camera rays, ``R`` basis functions, ``P`` scalars.

``loss_gradient`` (Eq. 10) never forms P images: with per-ray weights ``w = dz/dy[pixel] / spp``
(a box filter: a pixel is the mean of its rays),

    dz/dp = ∂/∂p Σ_rays w · W β [e + T L_phi(x') + sg(T)(e' + T' L_phi(x''))]   one Dr.Jit backward pass
          + Cᵀ v,   v_r = Σ_rays Σ_c w_c W β T_c B_{r,c}(x')                       (R,), then (P,)

with the fields detached. ``images`` forms the P images explicitly (forward mode, one pass per
scalar): the Jacobian of ``ndrf gradient`` and the check of the contraction above.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np
import torch

from schemas.methods import Method
from services.solver.estimators.methods.base import DIFFERENTIAL, RADIANCE, Fields, GradientMethod
from services.solver.estimators.problem import Problem
from services.solver.fields.field import evaluate
from services.solver.sampling.camera import CameraSamples, develop, sample_camera
from services.solver.sampling.incident import IncidentGeometry, evaluate_attached, evaluate_incident, sample_geometry
from services.solver.sampling.passes import passes_for
from services.solver.sampling.surface import queryable
from services.solver.sampling.tensors import color, field_query, mask, rgb, to_device, to_host
from services.solver.scene.params import FORWARD_GROUP  # scalars per forward-mode traversal of one graph
from services.solver.seeds import derive_seed

#: Camera rays per pass (two bounces each, and the head's R basis values at x').
RAYS_PER_PASS = 1 << 17


@dataclass
class HeadPass:
    """One pass of ``K`` camera rays and their two bounces (detached geometry, field values).

    scale        (K, 3)     W β per ray           first, second  the bounces from x and from x'
    l_first      (K, 3)     L_phi(x')             l_second       (K, 3) L_phi(x'')
    basis        (K, R, 3)  B(x') (zeros where x' is no surface of the domain)
    """

    samples: CameraSamples
    first: IncidentGeometry
    second: IncidentGeometry
    scale: torch.Tensor
    l_first: torch.Tensor
    l_second: torch.Tensor
    basis: torch.Tensor


class NdrfHead(GradientMethod):
    """``ndrf-rhs`` whose ``dL_theta`` is a :class:`~services.solver.fields.head.ParameterHead`
    (module docstring). Built by ``services.solver.optimize.build`` when ``training.head`` is set."""

    name = Method.NDRF_RHS
    uses = frozenset({RADIANCE, DIFFERENTIAL})

    def __init__(self) -> None:
        super().__init__(radiance=True, differential=True)

    def check(self, fields: Fields) -> None:
        if fields.radiance is None:
            raise ValueError(f"{self.name} needs a trained radiance field L_phi")
        if fields.head is None:
            raise ValueError("ndrf-rhs with training.head needs dL_theta as the many-parameter head")

    # ------------------------------------------------------------ camera pass

    def trace(self, problem: Problem, fields: Fields, sensor: mi.Sensor, spp: int, seed: int) -> HeadPass:
        """Camera rays, their bounce from ``x`` and from ``x'``, and the fields there."""
        head = fields.head
        assert head is not None and fields.radiance is not None  # self.check
        scene = problem.scene.scene
        samples, sampler = sample_camera(scene, sensor, spp, seed, problem.delta_depth)
        si = samples.chain.si
        with dr.suspend_grad():
            on_surface = samples.chain.active & queryable(si, scene)
            first = sample_geometry(scene, si, sampler, delta_depth=problem.delta_depth, active=on_surface)
            first.schedule()
            second = sample_geometry(scene, first.hit, sampler, delta_depth=problem.delta_depth,
                                     active=first.hit_surface)
            second.schedule()
        with torch.no_grad():
            hits, hits2 = mask(first.hit_surface), mask(second.hit_surface)
            query = field_query(first.hit)
            l_first = evaluate(fields.radiance, query, hits)
            l_second = evaluate(fields.radiance, field_query(second.hit), hits2)
            basis = evaluate(head.basis, query, hits).reshape(-1, head.rank, 3)
        scale = rgb(samples.weight * samples.chain.beta)
        return HeadPass(samples, first, second, scale, l_first, l_second, basis)

    def _attached(self, problem: Problem, p: HeadPass):
        """The estimate of the module docstring without its head term, attached to the BSDF
        parameters (call under ``ParameterSet.tracking``); non-finite lanes zeroed and counted."""
        scene = problem.scene.scene
        e1, t1 = evaluate_attached(scene, p.first, attach_bsdf=True, attach_emission=False)
        e2, t2 = evaluate_attached(scene, p.second, attach_bsdf=True, attach_emission=False)
        with dr.resume_grad():
            value = e1 + t1 * color(p.l_first) + dr.detach(t1) * (e2 + t2 * color(p.l_second))
            ok = dr.all(dr.isfinite(dr.detach(value)))
            value = dr.select(ok, value, 0.0)
        bad = dr.count(~ok)
        problem.count_sanitized("camera", int(np.asarray(bad).reshape(-1)[0]))
        return value, dr.select(ok, dr.detach(t1), 0.0)

    # ------------------------------------------------------------ entry points

    def loss_gradient(self, problem, fields, dz_dy, *, spp, seed, sensor=0):
        """Eq. 10 by one reverse-mode pass and ``Cᵀ v`` (module docstring): no P images."""
        self.check(fields)
        width, height = problem.scene.resolution(sensor)
        if dz_dy.shape != (height, width, 3):
            raise ValueError(f"dz/dy has shape {dz_dy.shape}, the film is {(height, width, 3)}")
        sensor_obj = problem.scene.sensor(sensor)
        if not sensor_obj.film().rfilter().is_box_filter():
            raise ValueError("ndrf-rhs with training.head contracts dz/dy per ray: it needs a box pixel filter")
        head = fields.head
        assert head is not None
        params = problem.parameters
        passes, per_pass = passes_for(width * height, spp, RAYS_PER_PASS)
        pixel = to_device(dz_dy.reshape(-1, 3), torch.float32)
        total = np.zeros(params.n)
        v = torch.zeros(head.rank, dtype=torch.float64)
        for k in range(passes):
            p = self.trace(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            weight = p.scale * pixel.repeat_interleave(per_pass, 0) / (per_pass * passes)   # (K, 3)
            with params.tracking():
                value, t1 = self._attached(problem, p)
                with dr.resume_grad():
                    dr.backward(dr.sum(dr.sum(value * color(weight), axis=None), axis=None))
                total += params.gradient_vector()
            v += torch.einsum("kc,krc->r", (weight * rgb(t1)).double(), p.basis.double())
        with torch.no_grad():
            total += to_host(head.coefficients.double().T @ v)
        return total

    def gradient_images(self, problem, fields, *, spp, seed, sensor=0):
        """``dI/dp`` ``(P, H, W, 3)``: one forward-mode pass per scalar plus the head's ``T C_k·B``
        per ray, splatted by the film. P images: for small P (tests, ``ndrf gradient``)."""
        self.check(fields)
        head = fields.head
        assert head is not None
        params = problem.parameters
        width, height = problem.scene.resolution(sensor)
        sensor_obj = problem.scene.sensor(sensor)
        passes, per_pass = passes_for(width * height, spp, RAYS_PER_PASS)
        out = np.zeros((params.n, height, width, 3))
        for k in range(passes):
            p = self.trace(problem, fields, sensor_obj, per_pass, derive_seed(seed, "camera", k))
            with params.tracking():
                _, t1 = self._attached(problem, p)
            rows = forward_grouped(problem, lambda p=p: [self._attached(problem, p)[0]], list(range(params.n)))
            d_exact = torch.stack([rgb(row[0]) for row in rows], 1)                          # (K, P, 3)
            with torch.no_grad():
                d_head = rgb(t1)[:, None, :] * head.combine(p.basis, head.coefficients)      # (K, P, 3)
            out += to_host(develop(sensor_obj, p.samples, p.scale[:, None, :] * (d_exact + d_head)))
        return (out / passes).astype(np.float32)




def forward_grouped(problem: Problem, evaluate_outputs, scalars: list[int]) -> list[list]:
    """``ParameterSet.forward`` of the outputs that ``evaluate_outputs()`` builds (attached, under
    tracking), for ``scalars``, in groups of :data:`FORWARD_GROUP` (one fresh graph per group):
    ``rows[i][j]`` = ``∂ output_j / ∂ p_{scalars[i]}``."""
    params = problem.parameters
    rows: list[list] = []
    for start in range(0, len(scalars), FORWARD_GROUP):
        with params.tracking():
            rows += params.forward(evaluate_outputs(), scalars[start:start + FORWARD_GROUP])
    return rows


def exact_vertex(problem: Problem, geometry: IncidentGeometry, scalars: list[int]):
    """``∂_k emitted`` and ``∂_k throughput`` of one bounce for the ``scalars`` (BSDF attached,
    emission detached): lists of ``mi.Color3f``; what the head's training source ``D_k(x')`` is made
    of (``services.solver.training.head``)."""
    scene = problem.scene.scene
    inc = evaluate_incident(scene, geometry, attach_bsdf=True, attach_emission=False)
    problem.count_sanitized("residual", inc.sanitized)
    rows = forward_grouped(problem, lambda: list(evaluate_attached(scene, geometry, attach_bsdf=True,
                                                                   attach_emission=False)), scalars)
    ok = inc.hit_surface | ~geometry.hit_surface  # lanes the guard kept (it only clears hit_surface)
    d_emitted = [dr.select(ok & dr.all(dr.isfinite(r[0])), r[0], 0.0) for r in rows]
    d_throughput = [dr.select(ok & dr.all(dr.isfinite(r[1])), r[1], 0.0) for r in rows]
    return d_emitted, d_throughput, inc.throughput

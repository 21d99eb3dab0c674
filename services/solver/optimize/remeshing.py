"""A shape job's remeshing schedule in the run (the recipe's :class:`~.recipe.Remesh`, the job's
``geometry.remesh_at``).

Before iteration ``k`` of the schedule, the run takes its answer, the estimate ``p̂``
(:mod:`.answer`), and for every optimized mesh:

1. its vertices ``v = (I + λL)⁻¹ û`` at the estimate's differential coordinates ``û``;
2. Botsch-Kobbelt remeshing of ``(v, F)`` to edges of ``edge`` times their mean length
   (:mod:`services.solver.scene.remesh`), ``(v', F')``;
3. the scene's mesh takes ``(v', F')``, a LargeSteps operator ``(I + λL')`` is built on ``F'``,
   and the parameter's scalars become ``u' = (I + λL') v'`` (``3 N'`` of them).

Then the vector ``p`` has another length, and what was sized by it starts again, as Mitsuba's
shape tutorial makes a new optimizer after its remesh: the optimizer (Adam's moments, with the
units and shared scales of the new spans), the answer (its window begins at ``k``: iterates of the
old triangles do not average with the new ones) and the learning rate's decay (its stage begins at
``k``: :meth:`~.recipe.Steps.learning_rate_at`). Every other parameter restarts from its estimate
too. A synthetic target keeps its surface (the Chamfer distance goes on), but it has no
differential coordinates on the new triangles: the shape's span of ``target_values`` is NaN.

The event (``remesh``, appended to ``plan.json``'s events) gives each mesh's vertices and
triangles before and after and the edge length. A checkpoint taken after a remesh holds each
remeshed mesh's triangles (:func:`topology`), and a resumed run rebuilds them before loading its
state (:func:`adopt`).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from services.solver.optimize.answer import answer_for
from services.solver.optimize.build import Built, build_optimizer
from services.solver.optimize.recipe import Decision, Recipe
from services.solver.optimize.resolve import derivative_layout
from services.solver.optimize.setup import Prepared
from services.solver.optimize.state import RunState
from services.solver.optimize.textures import TextureReport
from services.solver.scene.remesh import remesh
from services.solver.scene.shape import VERTICES, shape_of

log = logging.getLogger(__name__)


def remesh_run(k: int, prepared: Prepared, recipe: Recipe, built: Built, state: RunState) -> Decision:
    """Remesh every optimized mesh before iteration ``k`` (module docstring); returns the event."""
    assert recipe.remesh is not None   # the loop asks only at the recipe's iterations
    started = time.perf_counter()
    parameters = prepared.problem.parameters
    estimate = state.answer.estimate().values
    spans = parameters.offsets()
    meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    changes = []
    for shape, mesh in parameters.shapes.items():
        vertices = mesh.vertices(estimate[slice(*spans[f"{shape}.{VERTICES}"])])
        new = remesh(vertices, mesh.faces, recipe.remesh.edge, recipe.remesh.passes)
        meshes[shape] = (new.vertices, new.faces)
        changes.append(f"{shape}: {len(vertices)} vertices and {len(mesh.faces)} triangles -> {len(new.vertices)} and "
                       f"{len(new.faces)} (edges of {new.edge:.4g})")
    adopt(meshes, estimate, prepared, recipe, built, state, first=k)
    log.info("iteration %d: remeshed %s", k, "; ".join(changes))
    return Decision("remesh", ", ".join(f"{shape} {len(v)}" for shape, (v, _) in meshes.items()),
                    "; ".join(changes) + f", in {time.perf_counter() - started:.2f} s: the run goes on from its "
                    f"estimate, with a new optimizer, learning-rate stage and answer", k)


def adopt(meshes: dict[str, tuple[np.ndarray, np.ndarray]], values: np.ndarray, prepared: Prepared, recipe: Recipe,
          built: Built, state: RunState, *, first: int) -> None:
    """Make ``meshes`` (shape id -> vertices ``(N', 3)``, faces ``(F', 3)``) the optimized meshes
    and continue from ``values`` ``(P,)`` (the old layout's) at iteration ``first``: every array
    sized by ``p`` is rebuilt for the new layout (module docstring)."""
    parameters = prepared.problem.parameters
    old = parameters.offsets()
    before = (prepared.init, prepared.lower, prepared.upper, prepared.target_values, values)
    for shape, (vertices, faces) in meshes.items():
        parameters.remesh(shape, vertices, faces)
    init, lower, upper, target, start = [], [], [], [], []
    for key, (a, b) in old.items():
        mesh = shape_of(key)
        if mesh is not None and mesh in meshes:
            u = np.asarray(parameters.shapes[mesh].value, np.float64)
            init.append(u)
            start.append(u)
            lower.append(np.full(u.size, -np.inf))
            upper.append(np.full(u.size, np.inf))
            target.append(np.full(u.size, np.nan))   # no differential coordinates of the target on these triangles
        else:
            init.append(before[0][a:b])
            lower.append(before[1][a:b])
            upper.append(before[2][a:b])
            target.append(before[3][a:b] if before[3] is not None else np.zeros(b - a))
            start.append(before[4][a:b])
    prepared.init, prepared.lower, prepared.upper = np.concatenate(init), np.concatenate(lower), np.concatenate(upper)
    if prepared.target_values is not None:
        prepared.target_values = np.concatenate(target)
    prepared.textures = TextureReport(parameters)
    prepared.problem.layout = derivative_layout(parameters, None, prepared.spec.effects.merge_channels)
    built.optimizer = build_optimizer(prepared, recipe)
    state.answer = answer_for(recipe.steps.second_order, prepared.lower, prepared.upper, len(prepared.targets),
                              first=first)
    state.parameters = np.clip(np.concatenate(start), prepared.lower, prepared.upper)
    parameters.assign(state.parameters)


def topology(prepared: Prepared, state: RunState) -> dict[str, dict[str, np.ndarray]] | None:
    """What a checkpoint keeps of the remeshed meshes: each one's vertices as remeshed and its
    faces, by shape id; None when the run has not remeshed."""
    if not any(event.what == "remesh" for event in state.events):
        return None
    return {shape: {"vertices": mesh.v0, "faces": mesh.faces}
            for shape, mesh in prepared.problem.parameters.shapes.items()}


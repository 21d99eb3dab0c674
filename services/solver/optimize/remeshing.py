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
remeshed mesh's triangles (:meth:`.run.Run.topology`), and a resumed run rebuilds them before
loading its state (:func:`resumed`).
"""

from __future__ import annotations

import logging
import time
from dataclasses import replace

import numpy as np

from services.solver.optimize.answer import answer_for
from services.solver.optimize.build import build_optimizer
from services.solver.optimize.recipe import Decision
from services.solver.optimize.resolve import derivative_layout
from services.solver.optimize.run import Run
from services.solver.optimize.state import load, restore
from services.solver.scene.remesh import remesh
from services.solver.scene.shape import VERTICES, shape_of

log = logging.getLogger(__name__)


def remesh_run(k: int, run: Run) -> tuple[Run, Decision]:
    """Remesh every optimized mesh of ``run`` before iteration ``k`` (module docstring); returns
    the run that goes on and the event."""
    assert run.recipe.remesh is not None   # the loop asks only at the recipe's iterations
    started = time.perf_counter()
    parameters, remeshing = run.prepared.problem.parameters, run.recipe.remesh
    estimate = run.state.answer.estimate().values
    spans = parameters.offsets()
    meshes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    changes = []
    for shape, mesh in parameters.shapes.items():
        vertices = mesh.vertices(estimate[slice(*spans[f"{shape}.{VERTICES}"])])
        new = remesh(vertices, mesh.faces, remeshing.edge, remeshing.passes)
        meshes[shape] = (new.vertices, new.faces)
        changes.append(f"{shape}: {len(vertices)} vertices and {len(mesh.faces)} triangles -> {len(new.vertices)} and "
                       f"{len(new.faces)} (edges of {new.edge:.4g})")
    after = adopt(meshes, estimate, run, first=k)
    log.info("iteration %d: remeshed %s", k, "; ".join(changes))
    return after, Decision("remesh", ", ".join(f"{shape} {len(v)}" for shape, (v, _) in meshes.items()),
                           "; ".join(changes) + f", in {time.perf_counter() - started:.2f} s: the run goes on from "
                           f"its estimate, with a new optimizer, learning-rate stage and answer", k)


def adopt(meshes: dict[str, tuple[np.ndarray, np.ndarray]], values: np.ndarray, run: Run, *, first: int) -> Run:
    """The run that makes ``meshes`` (shape id -> vertices ``(N', 3)``, faces ``(F', 3)``) the
    optimized meshes and continues from ``values`` ``(P,)`` (``run``'s layout) at iteration
    ``first``: every array sized by ``p`` is new for the new layout (module docstring). ``run``
    keeps its arrays; the scene's meshes are replaced in place (the one thing both share)."""
    prepared, recipe = run.prepared, run.recipe
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
    prepared.problem.layout = derivative_layout(parameters, None, prepared.spec.effects.merge_channels)
    remeshed = replace(prepared, init=np.concatenate(init), lower=np.concatenate(lower),
                       upper=np.concatenate(upper),
                       target_values=None if prepared.target_values is None else np.concatenate(target))
    built = replace(run.built, optimizer=build_optimizer(remeshed, recipe))
    state = replace(run.state, answer=answer_for(recipe.steps.second_order, remeshed.lower, remeshed.upper,
                                                 len(remeshed.targets), first=first),
                    parameters=np.clip(np.concatenate(start), remeshed.lower, remeshed.upper))
    parameters.assign(state.parameters)
    return replace(run, prepared=remeshed, built=built, state=state)


def resumed(run: Run, blob: bytes) -> Run:
    """``run`` continued from the checkpoint ``blob`` (of its job): a checkpoint taken after a
    remesh first rebuilds its meshes (:func:`adopt`), then the state takes its values."""
    saved = load(run.prepared.spec, blob)
    if saved.get("meshes"):
        meshes = {shape: (np.asarray(mesh["vertices"], np.float64), np.asarray(mesh["faces"], np.int64))
                  for shape, mesh in saved["meshes"].items()}
        run = adopt(meshes, run.state.parameters, run, first=saved["remeshed_at"])
    restore(saved, run.state, run.built)
    return run

"""What a run carries from one iteration to the next (:class:`RunState`), how a checkpoint holds
it (``plan.json``, what is said of the run, is :mod:`.plan`'s).

A checkpoint (:mod:`.checkpoint`) holds the next iteration, the parameters, the optimizer's state
(Adam's moments; Levenberg-Marquardt's trust radius and its curvature with each view's remembered
Jacobians), the position in the stream of views, the batch in use, the answer's state, the
run's events, the fields' trainer and the triangles of a remeshed mesh.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from schemas.job import JobSpec
from services.solver.estimators.losses import BlurredLoss, ImageLoss
from services.solver.optimize import checkpoint
from services.solver.optimize.answer import Answer, answer_for
from services.solver.optimize.build import Built
from services.solver.optimize.images import ImageSchedule
from services.solver.optimize.recipe import BatchNow, Decision, Recipe
from services.solver.optimize.setup import Prepared


@dataclass
class RunState:
    """The run's state between iterations (module docstring). ``parameters`` ``(P,)`` are the
    values the next iteration is evaluated at (assigned to the scene by :meth:`advance`)."""

    next_iteration: int
    parameters: np.ndarray
    batch: BatchNow
    answer: Answer
    views_offset: int = 0
    events: list[Decision] = field(default_factory=list)   # decisions taken on the way
    images: ImageSchedule = field(default_factory=ImageSchedule)
    losses: dict[int, ImageLoss] = field(default_factory=dict)   # each view's loss (its target on the device)
    blurred: dict[int, BlurredLoss] = field(default_factory=dict)  # each view's last blurred loss
    auto_held: int = 0       # iterations in a row at which stop.auto's condition held (a resumed run re-earns them)

    def loss_of(self, prepared: Prepared, view: int, blur: float = 0.0) -> ImageLoss | BlurredLoss:
        """The loss of ``view`` against its target (made once: the target is kept on the device),
        on images blurred by ``blur`` pixels when > 0 (:mod:`.blur`; the blurred target is kept
        while the blur stays the same)."""
        if view not in self.losses:
            self.losses[view] = ImageLoss(prepared.spec.loss, prepared.targets[view],
                                          prepared.problem.count_sanitized)
        if blur <= 0:
            return self.losses[view]
        if view not in self.blurred or self.blurred[view].sigma != blur:
            self.blurred[view] = BlurredLoss(self.losses[view], blur)
        return self.blurred[view]

    @property
    def last_remesh(self) -> int:
        """The iteration of the run's last remesh (:mod:`.remeshing`), 0 when none."""
        return remesh_iteration(self.events)

    def advance(self, prepared: Prepared, updated: np.ndarray, views_offset: int) -> None:
        """Move to the next iteration at ``updated``: the one place the scene's parameters change."""
        self.parameters = np.asarray(updated, np.float64)
        self.views_offset = views_offset
        self.next_iteration += 1
        prepared.problem.parameters.assign(self.parameters)


def remesh_iteration(events: list[Decision]) -> int:
    """The iteration of the last ``remesh`` among ``events``, 0 when none."""
    return max((int(e.iteration) for e in events if e.what == "remesh" and e.iteration is not None), default=0)


def initial_state(prepared: Prepared, recipe: Recipe) -> RunState:
    """The state before the first iteration: the initial values, the recipe's first batch."""
    answer = answer_for(recipe.steps.second_order, prepared.lower, prepared.upper, len(prepared.targets))
    return RunState(0, prepared.init.copy(), BatchNow.first(recipe.batch), answer)


def save(spec: JobSpec, state: RunState, built: Built, method: str, meshes: dict | None = None) -> bytes:
    """The checkpoint of ``state`` (module docstring), with the triangles of the ``meshes`` a
    remesh replaced (:func:`.remeshing.topology`)."""
    trainer = built.trainer
    return checkpoint.dumps(spec=spec, next_iteration=state.next_iteration, parameters=state.parameters,
                            optimizer=built.optimizer.state_dict(), views_offset=state.views_offset,
                            batch=(state.batch.views, state.batch.spp, state.batch.gradient_spp),
                            events=[asdict(e) for e in state.events], answer=state.answer.state_dict(),
                            trainer=None if trainer is None else trainer.state_dict(), method=method, meshes=meshes)


def load(spec: JobSpec, blob: bytes) -> dict:
    """The checkpoint ``blob`` of ``spec``'s job as a dict (:mod:`.checkpoint`), with
    ``remeshed_at``: the iteration of its last remesh, 0 when none."""
    saved = checkpoint.loads(blob, spec)
    saved["remeshed_at"] = remesh_iteration([Decision(**e) for e in saved.get("events") or []])
    return saved


def restore(saved: dict, state: RunState, built: Built) -> None:
    """Continue from the checkpoint ``saved`` (:func:`load`): ``state`` and the built objects, of
    the checkpoint's layout (a remeshed one's rebuilt first, :meth:`.run.Run.restored`), take its
    values. A checkpoint of an older version keeps the curvature beside the optimizer's state."""
    state.events = [Decision(**e) for e in saved.get("events") or []]
    state.next_iteration = saved["next_iteration"]
    state.parameters = np.asarray(saved["parameters"], np.float64)
    state.views_offset = int(saved["views_offset"])
    state.batch = BatchNow(*(int(v) for v in saved["batch"]))
    if saved.get("answer") is not None:
        state.answer.load_state_dict(saved["answer"])
    optimizer = dict(saved["optimizer"])
    if built.optimizer.curvature is not None and "curvature" not in optimizer and saved.get("hessian") is not None:
        optimizer["curvature"] = {"hessian": saved["hessian"],
                                  "memory": saved.get("jacobians") or {}}
    built.optimizer.load_state_dict(optimizer)
    if built.trainer is not None and saved["trainer"] is not None:
        built.trainer.load_state_dict(saved["trainer"])

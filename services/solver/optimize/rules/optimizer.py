"""``auto``'s optimizer for a job of scalars or a pose (a mesh's vertices:
:func:`.geometry.shape_optimizer`).

Rule: Levenberg-Marquardt when the loss is ``l2`` and its Jacobian is cheap: at most
:data:`MAX_JACOBIAN_RENDERS` forward-mode renders per view (one per group of scalars that change
distinct RGB channels, :func:`.layout.jacobian_renders`), or a field query; for a pose at most
:data:`MAX_GEOMETRY_RENDERS` (one per pose scalar). Otherwise Adam: another loss has no
Gauss-Newton model, and a texture or the many-parameter head would need a P x P curvature from P
Jacobian images per view.

Why: Levenberg-Marquardt reaches the answer in a few steps where Adam is limited to the learning
rate per step.
"""

from __future__ import annotations

from schemas.job import JobSpec
from schemas.methods import Method
from services.solver.estimators.layout import DerivativeLayout
from services.solver.optimize.rules.inputs import Decide, Parameters
from services.solver.optimize.rules.layout import jacobian_renders

#: ``auto`` takes Levenberg-Marquardt when its Jacobian costs at most this many forward renders per view.
MAX_JACOBIAN_RENDERS = 4
#: ``auto`` takes Levenberg-Marquardt on geometry while its Jacobian costs at most this many forward
#: renders per view (two shapes' poses).
MAX_GEOMETRY_RENDERS = 12
#: The methods whose paths are Mitsuba's (forward-mode Jacobian renders, one per channel group).
PATH_METHODS = (Method.PRB, Method.PRB_PROJECTIVE, Method.DIRECT_PROJECTIVE)


def optimizer(spec: JobSpec, method: str, parameters: Parameters, layout: DerivativeLayout, decide: Decide) -> str:
    """The job's optimizer, ``auto`` resolved (module docstring)."""
    if spec.optimizer != "auto":
        return spec.optimizer
    if spec.loss != "l2":
        decide("optimizer", "adam", f"the {spec.loss} loss has no Gauss-Newton model")
    elif layout.active == 0:
        decide("optimizer", "adam", "no scalar changes the image: nothing to model")
    elif spec.training.head is not None:
        decide("optimizer", "adam", "training.head (the many-parameter head): a Gauss-Newton step would need P "
                                    "Jacobian images per view (services.solver.optimize.validate)")
    elif parameters.has_textures:
        decide("optimizer", "adam", f"a texture's {parameters.n} scalars: a Gauss-Newton step would solve with a "
                                    f"P x P curvature (services.solver.optimize.validate)")
    else:
        renders = jacobian_renders(layout) if method in PATH_METHODS and spec.jacobian == "method" else 0
        cap = MAX_GEOMETRY_RENDERS if parameters.has_geometry else MAX_JACOBIAN_RENDERS
        if parameters.has_geometry and renders <= cap:
            decide("optimizer", "levenberg-marquardt",
                   f"geometry: {renders} forward render(s) per view measure the Jacobian (one per pose scalar, at "
                   f"most {cap}); a pose is a handful of scalars whose image responds smoothly away from the "
                   f"silhouettes, where Gauss-Newton steps in a trust region tell good steps from bad ones")
            return "levenberg-marquardt"
        if renders > cap:
            decide("optimizer", "adam", f"the Jacobian would cost {renders} forward renders per view (more than "
                                        f"{cap}): Adam on the adjoint gradient")
            return "adam"
        cost = (f"{renders} forward render(s) per view measure the Jacobian ({layout.active} scalars in {renders} "
                f"channel group(s))" if renders else "the Jacobian is a field query")
        decide("optimizer", "levenberg-marquardt", f"{cost}: Gauss-Newton steps in a trust region reach the answer "
                                                   f"in fewer iterations than Adam's learning-rate-limited steps")
        return "levenberg-marquardt"
    return "adam"

"""The registry of gradient methods: one class per :class:`schemas.methods.Method`.

Each class declares its ``name``, the fields it can use (``uses``) and how chosen effects shape
it (``from_effects``); the trainer, `choose_effects`, the loop, the CLI, the tests and the bench read
this registry. The interface is documented once, in :mod:`.base`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from schemas.methods import Method
from services.solver.estimators.methods.base import Fields, GradientMethod, contract
from services.solver.estimators.methods.camera_hit import Direct, NdrfLhs, NdrfRhs, OneBounce, RadianceCache
from services.solver.estimators.methods.prb import Prb
from services.solver.estimators.methods.projective import DirectProjective, PrbProjective

if TYPE_CHECKING:
    from services.solver.estimators.render import PathDepth
    from services.solver.scene.effects import Effects

METHODS: dict[Method, type[GradientMethod]] = {cls.name: cls for cls in (NdrfLhs, NdrfRhs, RadianceCache, Direct, Prb,
                                                                             PrbProjective, DirectProjective)}

_missing = set(Method) - set(METHODS)
if _missing:  # a public name without an implementation is a programming error: fail at import
    raise ImportError(f"gradient methods without a class: {sorted(_missing)}")


def method_class(name: str | Method) -> type[GradientMethod]:
    try:
        return METHODS[Method(name)]
    except ValueError:
        raise ValueError(f"unknown gradient method {name!r}; known: {', '.join(METHODS)}") from None


def make_method(name: str | Method, effects: Effects | None = None, depth: PathDepth | None = None) -> GradientMethod:
    """The method ``name`` as the chosen effects shape it (see each class's ``from_effects``);
    ``depth`` is the path depth of path-traced methods (``prb`` refuses to be built without one)."""
    return method_class(name).from_effects(effects, depth)


__all__ = ["METHODS", "Fields", "GradientMethod", "OneBounce", "contract", "make_method", "method_class"]

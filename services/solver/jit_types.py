"""Loose static types for Dr.Jit and Mitsuba values.

Mitsuba chooses its variant (``llvm_ad_rgb``) at run time, and its stubs name one array type in
several ways (``mitsuba.Bool`` in a signature of ours, ``drjit.auto.ad.Bool`` in Mitsuba's own;
a Python float where a ``Float`` is declared is broadcast at run time but refused by the stubs).
Precise annotations would disagree with nearly every Mitsuba call, so the solver annotates Dr.Jit
values with these aliases: they tell a reader what a value is, and mypy checks everything around
them (plain Python, numpy, torch) while treating the value itself as ``Any``.
"""

from __future__ import annotations

from typing import Any, TypeAlias

#: ``mi.Bool``: one boolean per lane.
Bool: TypeAlias = Any
#: ``mi.Float``: one float per lane (or a Python float, broadcast).
Float: TypeAlias = Any
#: ``mi.Color3f`` / ``mi.Spectrum``: an RGB value per lane.
Color: TypeAlias = Any
#: ``mi.Point2f``, ``mi.Vector2i``, ``mi.Vector3f`` and the like: a small vector per lane.
Vector: TypeAlias = Any
#: ``mi.Sensor``, ``mi.ShapePtr``, ``mi.SurfaceInteraction3f`` and other Mitsuba objects whose
#: methods take the variant's arrays.
MitsubaObject: TypeAlias = Any

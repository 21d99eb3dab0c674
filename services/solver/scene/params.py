"""The optimized scalars ``p = (p_1, ..., p_n)`` of a scene.

A job names Mitsuba ``mi.traverse`` keys (``red.reflectance.value``); each key holds one or more
scalars (an RGB value counts 3, a roughness 1). :class:`ParameterSet` fixes their order once, reads
and writes them as one flat vector, and computes forward-mode derivatives of any Dr.Jit
expression with respect to each scalar: that is how ``∂_p f`` and ``∂_p E`` of Eq. 4 are obtained
from ``bsdf.eval`` / ``emitter.eval`` without a hand-written formula per BSDF.

Material and emitter properties are accepted, and not those of purely ideal-specular BSDFs
(a mirror's reflectance, a glass's IOR): rays are continued through such surfaces by detached
sampling, as in Mitsuba's ``prb``, so no derivative would reach them. A mesh's pose
(``<shape id>.to_world.translate`` / ``.rotate``, :mod:`.geometry`) is a *geometry* parameter: not
a traverse key, its scalars move the mesh's ``vertex_positions``, and only the methods that sample
the moving silhouettes (Mitsuba's projective integrators) differentiate it; every other method
refuses it (``services.solver.optimize.validate``). So is a mesh's shape,
``<shape id>.vertex_positions`` (:mod:`.shape`): a traverse key, but its scalars are the
``LargeSteps`` differential coordinates ``u`` of the vertices, not the vertices themselves.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, replace
from typing import Literal

import drjit as dr
import mitsuba as mi
import numpy as np

from services.solver.scene.geometry import POSE_KEYS, ShapePose, mesh_shapes, refusal, split_key
from services.solver.scene.shape import VERTICES, MeshReports, ShapeMesh, shape_of, write_topology

Owner = Literal["bsdf", "emitter", "geometry"]

#: Scalars (or units, :meth:`ParameterSet.units`) per forward-mode traversal of one AD graph.
#: Dr.Jit 1.5 crashes (a segmentation fault in ``dr.traverse``) on the fourth forward traversal of
#: a graph that reads a bitmap texture through evaluated virtual calls (measured: 3 traversals
#: run, 4 crash); a caller re-evaluates the graph per group.
FORWARD_GROUP = 3


@dataclass(frozen=True)
class ParameterInfo:
    """One differentiable scene parameter, as listed to users."""

    key: str
    size: int
    owner: Owner
    owner_type: str
    value: tuple[float, ...]
    #: ``(H, W, C)`` of a bitmap texture's ``data`` (a texture parameter); None for a value
    shape: tuple[int, ...] | None = None

    @property
    def texture(self) -> bool:
        return self.shape is not None


@dataclass(frozen=True)
class Scalar:
    """Component ``component`` of the parameter ``key``: one entry of the vector ``p``."""

    key: str
    component: int

    @property
    def label(self) -> str:
        return f"{self.key}[{self.component}]"


def _as_numpy(value) -> np.ndarray:
    return np.asarray(value, dtype=np.float64).reshape(-1)


def _like(template, flat: np.ndarray):
    """A Dr.Jit value of the same type and shape as ``template`` holding ``flat``, opaque: a
    one-element array would otherwise be a literal, a constant of the kernels that read it, and
    a new value a new kernel (or a new recording of a frozen render)."""
    value = type(template)(np.asarray(flat, dtype=np.float32).reshape(dr.shape(template)))
    dr.make_opaque(value)
    return value


def _owner(params: mi.SceneParameters, key: str):
    """The BSDF or emitter a parameter belongs to (walking up Mitsuba's object hierarchy)."""
    node = params.properties[key][2]  # (value, handle, node, flags)
    while node is not None:
        if isinstance(node, mi.BSDF):
            return "bsdf", node
        if isinstance(node, mi.Emitter):
            return "emitter", node
        node = params.hierarchy.get(node, (None, 0))[0]
    return None, None


def _is_optimizable(params: mi.SceneParameters, key: str) -> bool:
    # Mitsuba flags microfacet roughness "Discontinuous" (its sampling moves with it); with detached
    # sampling, as here and in prb, its derivative is still exact. Geometry is excluded by owner.
    if params.flags(key) & int(mi.ParamFlags.NonDifferentiable):
        return False
    if not dr.is_array_v(params[key]) or not dr.is_float_v(params[key]):
        return False
    kind, node = _owner(params, key)
    if kind == "bsdf" and not int(node.flags()) & int(mi.BSDFFlags.Smooth):
        return False  # ideal-specular BSDF: sampling is detached, no derivative would flow
    return kind is not None


def differentiable_parameters(params: mi.SceneParameters) -> list[ParameterInfo]:
    """Every material or emitter parameter of a scene that can be optimized, in traversal order."""
    out = []
    for key in params.keys():  # noqa: SIM118 (SceneParameters is not a dict)
        if not _is_optimizable(params, key):
            continue
        kind, node = _owner(params, key)
        value = _as_numpy(params[key])
        plugin = str(node).split("[", 1)[0].strip()  # e.g. SmoothDiffuse, AreaLight
        shape = texture_shape(params[key])
        if shape is not None:  # listed by its mean per channel: a texture's texels are not a list to show
            value = value.reshape(-1, shape[-1]).mean(axis=0)
        out.append(ParameterInfo(key, int(np.prod(dr.shape(params[key]))), kind, plugin,
                                 tuple(float(v) for v in value), shape))
    return out


def texture_shape(value) -> tuple[int, ...] | None:
    """``(H, W, C)`` when ``value`` is a bitmap texture's ``data`` (a 3-D tensor), else None."""
    shape = tuple(int(d) for d in dr.shape(value))
    return shape if isinstance(value, mi.TensorXf) and len(shape) == 3 else None


class ParameterSet(MeshReports):
    """The ordered optimized scalars of one scene, and forward-mode AD with respect to them.

    ``n`` is the number of scalars, ``P`` in the shapes written elsewhere (gradient images are
    ``P x H x W x 3``).
    """

    def __init__(self, params: mi.SceneParameters, keys: Sequence[str], largesteps_lambda: float = 19.0):
        if not keys:
            raise ValueError("at least one parameter key must be selected")
        if len(set(keys)) != len(keys):
            raise ValueError(f"parameter keys must be unique, got {list(keys)}")
        allowed = {info.key: info for info in differentiable_parameters(params)}
        meshes = set(mesh_shapes(params))
        #: the meshes whose pose is optimized, by shape id (:mod:`.geometry`)
        self.poses: dict[str, ShapePose] = {}
        #: the meshes whose vertices are optimized, by shape id (:mod:`.shape`)
        self.shapes: dict[str, ShapeMesh] = {}
        for key in keys:
            geometry = split_key(key)
            shape = shape_of(key)
            if shape is not None and shape in meshes:
                mesh = self.shapes[shape] = ShapeMesh.of(params, shape, largesteps_lambda)
                allowed[key] = ParameterInfo(key, mesh.size, "geometry", "Mesh", tuple(mesh.centre))
            elif geometry is not None and geometry[0] in meshes:
                shape, kind = geometry
                if shape not in self.poses:
                    self.poses[shape] = ShapePose.of(params, shape)
                allowed[key] = ParameterInfo(key, POSE_KEYS[kind], "geometry", "Mesh", (0.0,) * POSE_KEYS[kind])
            elif geometry is not None:
                raise ValueError(f"parameter {key!r}: {geometry[0]!r} is not a mesh of this scene (a pose moves a "
                                 f"mesh's vertex_positions); meshes: {', '.join(sorted(meshes)) or 'none'}")
            if key not in allowed:
                known = key in params.keys()  # noqa: SIM118 (SceneParameters is not a dict)
                reason = "is a key, but not a differentiable material or emitter parameter" if known else (
                    "is not a key of this scene")
                if known and type(params[key]).__name__ == "TensorXu8":
                    reason = ("is an 8-bit texture: Mitsuba keeps an 8-bit image file (PNG, JPEG) as integers, which "
                              "have no derivative; give the texture as a float image (EXR)")
                raise ValueError(f"parameter {key!r} {reason}; optimizable keys: {', '.join(allowed) or 'none'}")
        for shape in set(self.poses) & set(self.shapes):
            raise ValueError(f"parameter '{shape}.vertex_positions': the mesh's pose is optimized too; its vertices "
                             f"already move freely (optimize one or the other)")
        self.params = params
        self.keys = list(keys)
        #: the variables :meth:`tracking` enabled gradients on, by key (None outside it)
        self._leaves: dict[str, object] | None = None
        self.infos = [allowed[k] for k in self.keys]
        self.owners = {k: _owner(params, k)[1] for k in self.keys if k not in self._geometry_keys()}
        self.n = sum(info.size for info in self.infos)
        self._scalars: list[Scalar] | None = None

    @property
    def scalars(self) -> list[Scalar]:
        """One :class:`Scalar` per entry of ``p``, made on first use (a texture's million texels
        need none unless a per-scalar path asks for them)."""
        if self._scalars is None:
            self._scalars = [Scalar(k, c) for k, info in zip(self.keys, self.infos) for c in range(info.size)]
        return self._scalars

    @property
    def sizes(self) -> list[int]:
        """Scalars of each parameter, in order."""
        return [info.size for info in self.infos]

    @property
    def textures(self) -> list[tuple[str, tuple[int, ...]]]:
        """``(key, shape)`` of each texture parameter."""
        return [(info.key, info.shape) for info in self.infos if info.texture and info.shape is not None]

    @property
    def has_textures(self) -> bool:
        return any(info.texture for info in self.infos)

    @property
    def has_geometry(self) -> bool:
        """Whether a scalar moves a shape (a pose, or a mesh's vertices)."""
        return bool(self.poses or self.shapes)

    def _geometry_keys(self) -> set[str]:
        return {key for key in self.keys if (split := split_key(key)) is not None and split[0] in self.poses
                or self._mesh(key) is not None}

    @property
    def geometry(self) -> list[bool]:
        """Per scalar: whether it moves a shape."""
        return [info.owner == "geometry" for info in self.infos for _ in range(info.size)]

    def step_units(self) -> np.ndarray:
        """Per scalar, ``(n,)``: the size of one unit of the optimizer's steps in the scalar's own
        units. 1 but for a pose, whose steps are measured in the size of its shape: a translation
        in the shape's radius ``r`` about its centre (scene units), a rotation in radians
        (``180 / pi`` degrees, which move the farthest vertex by ``r``): a learning rate then means
        the same share of the shape for both, and for a bunny as for a building."""
        out: list[float] = []
        for key, info in zip(self.keys, self.infos):
            geometry = split_key(key) if info.owner == "geometry" else None
            unit = 1.0
            if (mesh := self._mesh(key)) is not None:   # differential coordinates: in radii, as a translation
                unit = mesh.radius or 1.0
            elif geometry is not None:
                radius = self.poses[geometry[0]].radius or 1.0
                unit = radius if geometry[1] == "to_world.translate" else 180.0 / np.pi
            out += [unit] * info.size
        return np.asarray(out, np.float64)

    @property
    def labels(self) -> list[str]:
        return [s.label for s in self.scalars]

    def owner_kinds(self) -> dict[str, Owner]:
        return {info.key: info.owner for info in self.infos}

    # ------------------------------------------------------------------ values

    def values(self) -> np.ndarray:
        """The current scalars as one float64 vector of shape ``(n,)``."""
        return np.concatenate([_as_numpy(self._get(k)) for k in self.keys])

    def _get(self, key: str):
        """The Dr.Jit value of ``key``: a traverse key's, or a pose's own (:mod:`.geometry`)."""
        geometry = split_key(key)
        if (mesh := self._mesh(key)) is not None:
            return mesh.value
        if geometry is not None and geometry[0] in self.poses:
            return self.poses[geometry[0]].values[geometry[1]]
        return self.params[key]

    def _set(self, key: str, value) -> None:
        geometry = split_key(key)
        if (mesh := self._mesh(key)) is not None:
            mesh.value = value
        elif geometry is not None and geometry[0] in self.poses:
            self.poses[geometry[0]].values[geometry[1]] = value
        else:
            self.params[key] = value

    def _update(self) -> None:
        """Move the posed meshes to their poses' values, then let Mitsuba update the scene."""
        for pose in self.poses.values():
            pose.write(self.params)
        for mesh in self.shapes.values():
            mesh.write(self.params)
        self.params.update()

    def variable(self, key: str):
        """The variable forward mode seeds for ``key``: inside :meth:`tracking` its leaf."""
        return self._leaves[key] if self._leaves is not None else self._get(key)

    def poses_of(self, values: np.ndarray) -> dict[str, dict[str, np.ndarray]]:
        """``{shape: {kind: (3,)}}`` of the poses in the flat vector ``values``."""
        out: dict[str, dict[str, np.ndarray]] = {shape: {kind: np.zeros(3) for kind in POSE_KEYS}
                                                 for shape in self.poses}
        offset = 0
        for key, info in zip(self.keys, self.infos):
            geometry = split_key(key) if info.owner == "geometry" else None
            if geometry is not None:
                out[geometry[0]][geometry[1]] = np.asarray(values[offset:offset + info.size], np.float64)
            offset += info.size
        return out

    def remesh(self, shape: str, vertices: np.ndarray, faces: np.ndarray) -> ShapeMesh:
        """Replace the optimized mesh ``shape`` by ``vertices`` ``(N', 3)`` and ``faces`` ``(F', 3)``
        (a remesh, :mod:`.remesh`): the scene's mesh takes them, a LargeSteps operator of the same
        λ is built on them, and the parameter's scalars become their ``3 N'`` differential
        coordinates. ``n`` changes; the other parameters keep their order and values."""
        old = self.shapes[shape]
        write_topology(self.params, shape, vertices, faces)
        mesh = self.shapes[shape] = ShapeMesh.of(self.params, shape, old.lambda_)
        mesh.target = old.target
        i = self.keys.index(f"{shape}.{VERTICES}")
        self.infos[i] = replace(self.infos[i], size=mesh.size, value=tuple(mesh.centre))
        self.n, self._scalars = sum(info.size for info in self.infos), None
        return mesh

    def refuse(self, before: np.ndarray, after: np.ndarray) -> str | None:
        """Why the step from ``before`` to ``after`` (flat vectors) may not be written: non-finite
        vertices or inverted triangles of a posed or reshaped mesh (:func:`.geometry.refusal`); None
        when it may."""
        for key, (start, stop) in self.offsets().items():
            if (mesh := self._mesh(key)) is not None:
                why = refusal(mesh.vertices(before[start:stop]), mesh.vertices(after[start:stop]), mesh.faces)
                if why is not None:
                    return f"{mesh.shape}: {why}"
        if not self.poses:
            return None
        old, new = self.poses_of(before), self.poses_of(after)
        for shape, pose in self.poses.items():
            why = refusal(pose.vertices(**_kw(old[shape])), pose.vertices(**_kw(new[shape])), pose.faces)
            if why is not None:
                return f"{shape}: {why}"
        return None

    def pose_reports(self, values: np.ndarray) -> list[dict]:
        """Each posed mesh's pose in ``values``: its 4x4 matrix and XML (:meth:`.ShapePose.report`)."""
        poses = self.poses_of(values)
        return [pose.report(**_kw(poses[shape])) for shape, pose in self.poses.items()]

    def assign(self, values: np.ndarray) -> None:
        """Write the flat vector ``values`` (shape ``(n,)``) into the scene."""
        values = np.asarray(values, dtype=np.float64).reshape(-1)
        if values.size != self.n:
            named = f" ({', '.join(self.labels)})" if self.n <= 64 else ""
            raise ValueError(f"expected {self.n} values{named}, got {values.size}")
        if not np.all(np.isfinite(values)):
            bad = np.flatnonzero(~np.isfinite(values))
            raise ValueError(f"refusing to write non-finite parameter values ({bad.size} of {values.size}, first at "
                             f"index {int(bad[0])}: {values[bad[0]]})")
        offset = 0
        for key, info in zip(self.keys, self.infos):
            self._set(key, _like(self._get(key), values[offset:offset + info.size]))
            offset += info.size
        self._update()

    def split(self, flat: np.ndarray) -> dict[str, list[float]]:
        """``{key: [scalars]}`` view of a flat vector (for reports)."""
        out, offset = {}, 0
        for key, info in zip(self.keys, self.infos):
            out[key] = [float(v) for v in np.asarray(flat).reshape(-1)[offset:offset + info.size]]
            offset += info.size
        return out

    # ------------------------------------------------------------- derivatives

    @contextmanager
    def tracking(self) -> Iterator[None]:
        """Enable gradient tracking on the selected parameters for the duration of the block.

        Each parameter is given a fresh leaf variable with its values (what ``mi.ad.Adam`` gives
        Mitsuba's tutorial loop), and :meth:`gradients` reads those leaves: ``params[key]`` is a
        view of the object's own field, which ``params.update()`` may replace by a variable derived
        from the leaf. An environment map does: it stores its data with its wrap-around columns
        refreshed, so after the update ``params[key]`` is that copy; enabling gradients on the
        field in place left the copy without an edge to it, and ``dz/dp`` came out zero."""
        leaves = {}
        for key in self.keys:
            value = self._get(key)
            leaf = type(value)(value)       # a new variable over the same values (no copy of the data)
            dr.enable_grad(leaf)
            self._set(key, leaf)
            leaves[key] = leaf
        self._update()
        self._leaves = leaves
        try:
            yield
        finally:
            self._leaves = None
            for key, leaf in leaves.items():
                self._set(key, dr.detach(leaf))
            self._update()

    def gradients(self) -> list:
        """``dz/dp`` of each key (value-shaped Dr.Jit arrays) left by a backward pass inside
        :meth:`tracking`, then cleared there."""
        if self._leaves is None:
            raise RuntimeError("gradients() reads the variables tracking() enabled: call it inside tracking()")
        grads = [dr.grad(self._leaves[key]) for key in self.keys]
        for key in self.keys:
            dr.clear_grad(self._leaves[key])
        return grads

    def gradient_vector(self) -> np.ndarray:
        """:meth:`gradients` evaluated and flattened in the layout of the scalars: ``(P,)`` float64."""
        grads = self.gradients()
        dr.eval(*grads)
        return np.concatenate([np.asarray(g, np.float64).reshape(-1) for g in grads])

    def tangent(self, index: int) -> tuple[str, object]:
        """The one-hot tangent selecting scalar ``index``: ``(key, value-shaped array)``."""
        scalar = self.scalars[index]
        template = self._get(scalar.key)
        onehot = np.zeros(_as_numpy(template).size)
        onehot[scalar.component] = 1.0
        return scalar.key, _like(template, onehot)

    def tangents(self, indices: Sequence[int]) -> dict[str, object]:
        """The tangent selecting the sum of scalars ``indices``: ``{key: value-shaped array}`` with
        a 1 at each selected component (one forward-mode pass then gives ``Σ_i ∂/∂p_i``)."""
        selected = np.zeros(self.n)
        selected[np.asarray(list(indices), dtype=np.int64)] = 1.0     # vectorised: a texture has millions
        out, offset = {}, 0
        for key, info in zip(self.keys, self.infos):
            part = selected[offset:offset + info.size]
            offset += info.size
            if part.any():
                out[key] = _like(self._get(key), part)
        return out

    def units(self) -> list[list[int]]:
        """The scalars as the effect probe measures them: every scalar of a value alone, every
        texture as one unit (all its texels: one forward-mode traversal, not one per texel)."""
        out, offset = [], 0
        for info in self.infos:
            if info.texture:
                out.append(list(range(offset, offset + info.size)))
            else:
                out += [[offset + c] for c in range(info.size)]
            offset += info.size
        return out

    def forward_units(self, outputs: Sequence, units: Sequence[Sequence[int]]) -> list[list]:
        """:meth:`forward` along the summed tangent of each unit (``Σ_{i in unit} ∂/∂p_i``):
        ``grads[u][j]``. Call inside :meth:`tracking`, as :meth:`forward`."""
        keep = dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput
        grads = []
        for position, unit in enumerate(units):
            tangents = self.tangents(unit)
            for key, tangent in tangents.items():
                dr.set_grad(self.variable(key), tangent)
            dr.enqueue(dr.ADMode.Forward, *[self.variable(key) for key in tangents])
            dr.traverse(dr.ADMode.Forward, flags=keep if position + 1 < len(units) else dr.ADFlag.Default)
            row = [dr.grad(o) for o in outputs]
            dr.eval(row)
            grads.append(row)
            for o in outputs:
                dr.clear_grad(o)
            for key in tangents:
                dr.clear_grad(self.variable(key))
        return grads

    def forward(self, outputs: Sequence, scalars: Sequence[int] | None = None) -> list[list]:
        """Forward-mode derivatives ``∂ output / ∂ p_i`` for every scalar ``i`` (or the listed ones).

        Call inside :meth:`tracking`, after ``outputs`` were computed with AD enabled (sampling
        detached, evaluation attached). The AD graph is traversed once per scalar and kept until
        the last one. Returns ``grads[i][j]`` = derivative of ``outputs[j]`` w.r.t. scalar ``i``.
        """
        order = list(range(self.n)) if scalars is None else list(scalars)
        return self.forward_units(outputs, [[i] for i in order])


def _kw(pose: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """A pose's values as :meth:`.ShapePose.vertices` takes them."""
    return {"translate": pose["to_world.translate"], "rotate": pose["to_world.rotate"]}

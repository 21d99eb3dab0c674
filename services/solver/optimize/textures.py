"""Texture parameters in the loop's reports: a bitmap's ``data`` is one parameter of ``H x W x C``
scalars, optimized like any other (``prb``'s adjoint pass gives ``dz/dp`` for all of them at once),
but never listed scalar by scalar.

The optimized vector ``p`` (``(P,)``) is the concatenation of every parameter's scalars, texels
included. :class:`TextureReport` splits it for the reports:

* the *listed* scalars (every parameter that is not a texture) keep their place in ``plan.json``
  (``scalars``, ``init``, ``lower``, ``upper``, ``target_values``), in each iteration record
  (``parameters``, ``updated_parameters``, ``dz_dp``) and in the summary, as before;
* a shape parameter (a mesh's vertices, ``services.solver.scene.shape``) is not listed either:
  the records report its Chamfer distance to a synthetic target mesh, and its differential
  coordinates are left out of the records' ``parameter_error`` and ``estimate_error``
  (:meth:`TextureReport.error`: a target of another topology has none);
* each texture is reported by a summary per iteration (:meth:`TextureReport.summaries`: mean per
  channel, min, max, gradient RMS and, against a synthetic target, RMSE and PSNR) and by its value
  ``(H, W, C)`` float32 (:meth:`TextureReport.images`), written to files by the host; its
  gradient ``dz/dp`` is itself a texture of the same shape (:meth:`TextureReport.gradients`),
  never a ``P x H x W x 3`` stack of images.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from services.solver.scene.params import ParameterSet


@dataclass(frozen=True)
class Texture:
    """A texture parameter's place in ``p``: entries ``offset .. offset + size`` reshape to ``shape``."""

    key: str
    shape: tuple[int, ...]   # (H, W, C)
    offset: int

    @property
    def size(self) -> int:
        return int(np.prod(self.shape))

    def of(self, flat: np.ndarray) -> np.ndarray:
        """This texture's entries of ``flat`` ``(P,)`` as ``(H, W, C)`` float32."""
        return np.asarray(flat[self.offset:self.offset + self.size], np.float32).reshape(self.shape)


class TextureReport:
    """The split of one job's ``p`` into listed scalars and textures (module docstring)."""

    def __init__(self, parameters: ParameterSet):
        self.textures: list[Texture] = []
        unlisted = {f"{shape}.vertex_positions" for shape in parameters.shapes}
        mask = np.ones(parameters.n, dtype=bool)
        self.labels: list[str] = []
        offset = 0
        for info in parameters.infos:
            if info.shape is not None:
                self.textures.append(Texture(info.key, info.shape, offset))
                mask[offset:offset + info.size] = False
            elif info.key in unlisted:   # a mesh's vertices: reported by their Chamfer distance, not listed
                mask[offset:offset + info.size] = False
            else:
                self.labels += [f"{info.key}[{c}]" for c in range(info.size)]
            offset += info.size
        self.listed = mask
        #: the scalars that are not a shape's: the listed ones and the textures' texels
        self.compared = mask.copy()
        for texture in self.textures:
            self.compared[texture.offset:texture.offset + texture.size] = True
        self.n = parameters.n

    def __bool__(self) -> bool:
        return bool(self.textures)

    @property
    def texels(self) -> int:
        """Texels of every texture (a texel of an RGB texture holds three scalars)."""
        return sum(t.shape[0] * t.shape[1] for t in self.textures)

    def scalars(self, flat: np.ndarray) -> list[float]:
        """The listed scalars of ``flat`` ``(P,)`` (every scalar when the job has no texture)."""
        return np.asarray(flat, np.float64)[self.listed].tolist()

    def error(self, flat: np.ndarray, target: np.ndarray | None) -> float | None:
        """``max |flat - target|`` over the scalars that are not a shape's (:attr:`compared`; both
        ``(P,)``): a record's ``parameter_error`` or ``estimate_error``. None without a synthetic
        target, or when every scalar is a shape's (its error is its Chamfer distance)."""
        if target is None or not self.compared.any():
            return None
        return float(np.max(np.abs(np.asarray(flat, np.float64)[self.compared] - target[self.compared])))

    def images(self, flat: np.ndarray) -> dict[str, np.ndarray]:
        """Every texture's value ``(H, W, C)`` float32, by key."""
        return {t.key: t.of(flat) for t in self.textures}

    def targets(self, target: np.ndarray | None) -> dict[str, np.ndarray]:
        """Every texture's synthetic target ``(H, W, C)`` float32, by ``<key>.target`` (none
        without synthetic targets)."""
        return {} if target is None else {f"{t.key}.target": t.of(target) for t in self.textures}

    def gradients(self, dz_dp: np.ndarray) -> dict[str, np.ndarray]:
        """Every texture's gradient ``dz/dp`` as a texture ``(H, W, C)`` float32, by key."""
        return {f"{t.key}.dz_dp": t.of(dz_dp) for t in self.textures}

    def summaries(self, flat: np.ndarray, dz_dp: np.ndarray | None = None,
                  target: np.ndarray | None = None) -> dict[str, dict]:
        """Per texture: ``mean`` (per channel), ``min``, ``max``, ``gradient_rms`` (of ``dz_dp``) and,
        with a synthetic ``target``, ``rmse`` and ``psnr`` (dB, peak 1 or the target's maximum if
        larger, as for an emitter's radiance)."""
        out = {}
        for t in self.textures:
            value = t.of(flat).astype(np.float64)
            summary: dict = {"shape": list(t.shape),
                             "mean": value.reshape(-1, t.shape[-1]).mean(axis=0).tolist(),
                             "min": float(value.min()), "max": float(value.max())}
            if dz_dp is not None:
                summary["gradient_rms"] = float(np.sqrt(np.mean(t.of(dz_dp).astype(np.float64) ** 2)))
            if target is not None:
                summary.update(texture_error(value, t.of(target)))
            out[t.key] = summary
        return out

    def plan(self, init: np.ndarray, lower: np.ndarray, upper: np.ndarray,
             target: np.ndarray | None) -> list[dict]:
        """What ``plan.json`` says of each texture: key, shape, texels, bounds, the initial value's
        summary and, for synthetic targets, the target's."""
        out = []
        for t in self.textures:
            entry: dict = {"key": t.key, "shape": list(t.shape), "texels": t.shape[0] * t.shape[1],
                           "lower": float(lower[t.offset]),
                           "upper": float(upper[t.offset]) if np.isfinite(upper[t.offset]) else None,
                           "init": self.summaries(init)[t.key]}
            if target is not None:
                entry["target"] = self.summaries(target)[t.key]
            out.append(entry)
        return out


def texture_error(value: np.ndarray, target: np.ndarray) -> dict:
    """``rmse`` and ``psnr`` (dB) of a texture against its target, same shapes; the PSNR's peak is
    1 (a reflectance) or the target's maximum when larger."""
    mse = float(np.mean((np.asarray(value, np.float64) - np.asarray(target, np.float64)) ** 2))
    peak = max(1.0, float(np.max(target)))
    psnr = float("inf") if mse == 0.0 else 10.0 * np.log10(peak * peak / mse)
    return {"rmse": mse ** 0.5, "psnr": min(psnr, 200.0)}


def record_fields(report: TextureReport, parameters: np.ndarray, updated: np.ndarray, dz_dp: np.ndarray,
                  target: np.ndarray | None) -> dict:
    """The fields of an :class:`~schemas.records.IterationRecord` that hold ``p``: the listed
    scalars of ``parameters``, ``updated`` and ``dz_dp`` (all ``(P,)``), and the textures'
    summaries (None for a job without a texture)."""
    return {"parameters": report.scalars(parameters), "updated_parameters": report.scalars(updated),
            "dz_dp": report.scalars(dz_dp),
            "textures": report.summaries(parameters, dz_dp, target) if report else None}

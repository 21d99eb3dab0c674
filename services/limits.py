"""Caps on untrusted jobs (pure logic; the API maps a violation to a 4xx naming the limit)."""

from __future__ import annotations

from schemas.job import ImageTargets, JobSpec, PathScene, SyntheticTargets
from services.errors import JobError
from services.settings import Limits


def check_limits(spec: JobSpec, limits: Limits) -> None:
    """Raise :class:`JobError` for the first field over a cap (or a source the service refuses)."""
    if isinstance(spec.scene, PathScene):
        raise JobError("scene.path", "the service does not read host paths: send {'xml': ..., 'files': {...}} "
                                     "(ndrf submit packs a local scene)")
    if spec.render.resolution is not None:
        width, height = spec.render.resolution
        if max(width, height) > limits.resolution:
            raise JobError("render.resolution", f"{width}x{height} exceeds the limit of {limits.resolution} "
                                                f"pixels per side (NDRF_MAX_RESOLUTION)")
    for field, spp in (("render.spp", spec.render.spp), ("render.gradient_spp", spec.render.gradient_spp)):
        if spp > limits.spp:
            raise JobError(field, f"{spp} exceeds the limit of {limits.spp} samples per pixel (NDRF_MAX_SPP)")
    if isinstance(spec.targets, SyntheticTargets) and spec.targets.synthetic.spp > limits.spp:
        raise JobError("targets.synthetic.spp", f"{spec.targets.synthetic.spp} exceeds the limit of {limits.spp} "
                                                f"samples per pixel (NDRF_MAX_SPP)")
    if spec.iterations > limits.iterations:
        raise JobError("iterations", f"{spec.iterations} exceeds the limit of {limits.iterations} (NDRF_MAX_ITERATIONS)")
    if len(spec.parameters) > limits.parameters:
        raise JobError("parameters", f"{len(spec.parameters)} parameters exceed the limit of {limits.parameters} "
                                     f"scalars (NDRF_MAX_PARAMETERS)")
    lanes = spec.training.residual_points * spec.training.incident_samples
    if lanes > limits.training_points:
        raise JobError("training.residual_points", f"N x M = {lanes} exceeds the limit of {limits.training_points} "
                                                   f"(NDRF_MAX_TRAINING_POINTS)")
    if isinstance(spec.targets, ImageTargets):
        for i, image in enumerate(spec.targets.images):
            if len(image.data) * 3 // 4 > limits.upload_bytes:
                raise JobError(f"targets.images[{i}].data", f"image exceeds the upload limit of {limits.upload_bytes} bytes")

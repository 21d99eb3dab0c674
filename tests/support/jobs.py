"""Small jobs the tests run in-process (``ndrf run``'s path), in one place."""

from __future__ import annotations

SMALL_TRAINING = {"residual_points": 512, "incident_samples": 4, "warmup_steps": 10, "steps_per_iteration": 2}


def small_job(method="direct", iterations=6, **extra):
    job = {
        "scene": {"builtin": "cornell-box"},
        "parameters": [{"key": "red.reflectance.value", "init": [0.2, 0.2, 0.2]}],
        "targets": {"synthetic": {"values": {"red.reflectance.value": [0.57, 0.04, 0.04]}, "spp": 32}},
        "method": method,
        "iterations": iterations,
        "learning_rate": 0.05,
        "render": {"spp": 4, "gradient_spp": 4, "resolution": [16, 16]},
        "training": SMALL_TRAINING,
        "checkpoint_every": 2,
        "seed": 3,
    }
    job.update(extra)
    return job


def run_job(job, folder, **options):
    """The job run in-process into ``folder``, as ``ndrf run`` does; returns its summary."""
    from schemas.job import JobSpec
    from services.jobs.local import run_local

    return run_local(JobSpec.model_validate(job), folder, **options)


def small_room_job(**extra) -> dict:
    """``room-open-8`` at 16x16: the walls' and the sphere's albedo from 0.5 grey, 16-spp targets
    (the default recipe's tests: batches of views, the answer, the stop)."""
    job = {"scene": {"builtin": "room-open-8"},
           "parameters": [{"key": "walls.reflectance.value", "init": [0.5, 0.5, 0.5]},
                          {"key": "ball.reflectance.value", "init": [0.5, 0.5, 0.5]}],
           "targets": {"synthetic": {"values": {"walls.reflectance.value": [0.85, 0.85, 0.85],
                                                "ball.reflectance.value": [0.8, 0.2, 0.1]}, "spp": 16}},
           "render": {"resolution": [16, 16]}}
    return {**job, **extra}

"""Does a better sampler lower ``prb``'s gradient noise per sample? Mitsuba's samplers on one job.

``python -m bench.investigations.samplers [--job hidden-object] [--spp 8] [--draws 40]``

``prb``'s gradient noise is what the answer's standard error averages down (and, before the
answer was an estimate, the noise floor a run ended on). Beyond more samples, a sampler that
spreads its samples better (stratified, multi-jittered, orthogonal arrays, low discrepancy) could
lower the noise per sample: the antithetic idea, built into Mitsuba. For each sampler, the scene's
sensors take it with ``--spp`` samples per pixel (Mitsuba rounds some counts: stratified and
orthogonal to 9, low discrepancy to 16), and ``--draws`` gradients of the l2 loss against a
target at 90% of the truth's brightness are taken with independent seeds at the true values
(64 x 64 views). Reported per sampler: the samples it took, the gradient's relative standard
deviation per scalar, and the noise per sample: ``std x sqrt(spp)`` relative to the independent
sampler's (below 1: less noise for the same samples).
"""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from bench.common import machine, markdown_table, write_markdown

log = logging.getLogger(__name__)

ROOT = Path(__file__).resolve().parents[2]
SAMPLERS = ("independent", "stratified", "multijitter", "orthogonal", "ldsampler")


def gradients(job: dict, sampler: str, spp: int, draws: int) -> tuple[np.ndarray, int]:
    import drjit as dr

    from services.solver.backend import use_mitsuba
    from services.solver.scene.builtin import builtin_scene

    mi = use_mitsuba()
    scene_dict = builtin_scene(job["scene"]["builtin"])
    for value in scene_dict.values():
        if isinstance(value, dict) and value.get("type") == "perspective":
            value["sampler"] = {"type": sampler, "sample_count": spp}
            value["film"]["width"] = value["film"]["height"] = 64
    scene = mi.load_dict(scene_dict)
    params = mi.traverse(scene)
    keys = [p["key"] for p in job["parameters"]]
    for key in keys:
        params[key] = type(params[key])(job["targets"]["synthetic"]["values"][key])
    params.update()
    integrator = mi.load_dict({"type": "prb", "max_depth": -1, "rr_depth": 5})
    target = mi.TensorXf(np.array(mi.render(scene, params, integrator=integrator, spp=256, seed=99))[..., :3] * 0.9)
    taken = int(scene.sensors()[0].sampler().sample_count())
    out = []
    for k in range(draws):
        for key in keys:
            dr.enable_grad(params[key])
        params.update()
        image = mi.render(scene, params, integrator=integrator, spp=taken, seed=k, seed_grad=10**6 + k)
        dr.backward(dr.mean(dr.square(image[..., :3] - target)))
        out.append(np.concatenate([np.array(dr.grad(params[key])).ravel() for key in keys]))
        for key in keys:
            dr.clear_grad(params[key])
            dr.disable_grad(params[key])
    return np.array(out), taken


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.samplers", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--job", default="hidden-object")
    parser.add_argument("--spp", type=int, default=8)
    parser.add_argument("--draws", type=int, default=40)
    parser.add_argument("--out", type=Path, default=ROOT / "bench" / "results" / "samplers.json")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    job = json.loads((ROOT / "examples" / f"{args.job}.json").read_text())
    rows, reference = {}, None
    for sampler in SAMPLERS:
        g, taken = gradients(job, sampler, args.spp, args.draws)
        relative = g.std(0) / np.abs(g.mean(0))
        per_sample = g.std(0) * np.sqrt(taken)
        reference = per_sample if reference is None else reference
        rows[sampler] = {"spp": taken, "relative_std": relative.tolist(), "noise_per_sample": (per_sample /
                                                                                              reference).tolist()}
        log.info("%s (%d spp): relative std %s", sampler, taken, np.round(relative, 3))
    text = markdown_table(["sampler", "spp", "relative std of dz/dp (per scalar)", "noise per sample vs independent"],
                          [[name, r["spp"], ", ".join(f"{v:.3f}" for v in r["relative_std"]),
                            ", ".join(f"{v:.2f}" for v in r["noise_per_sample"])] for name, r in rows.items()])
    args.out.write_text(json.dumps({"machine": machine(), "job": args.job, "draws": args.draws, "rows": rows},
                                   indent=1))
    write_markdown(args.out, "bench.investigations.samplers", argv, text)
    log.info("\n%s", text)


if __name__ == "__main__":
    main()

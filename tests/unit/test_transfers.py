"""No host round trip inside an iteration: what a training step and a field query move through host
memory, counted by tests/support/transfers.py (on the CPU too: each counted call is a copy between
the GPU and the host on CUDA).

Allowed, and nothing else:

* a training step: scalar reads of torch (the loss, the gradient norm: one element each) and the
  parameter vector read from the scene (``P`` elements: is a batch stale?);
* a field query (the ``ndrf-lhs`` gradient at the cached first hits, the candidate image, the
  ``ndrf-rhs`` gradient at fresh camera hits): its input, the pixel gradient ``dz/dy`` (one
  ``H·W·3`` copy to the device), and its output (``dz/dp``, ``P`` elements; the candidate image),
  plus the same scalar and parameter reads.

A lane of Dr.Jit reaching torch through numpy (the hand-over before DLPack), or a per-ray tensor
read back to the host, fails these tests. On CUDA (``NDRF_DEVICE=cuda``, bench/gpu_check.sh)
the torch profiler also counts the host<->device copies of every library in the process (CUPTI),
Dr.Jit's included, and none larger than the allowed ones may appear.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from tests.support.transfers import Ledger, host_transfers

RESOLUTION = (64, 64)   # 4096 pixels, 16384 rays at 4 spp: a lane array is 64 KiB, far above COPY_BYTES
KEYS = ["red.reflectance.value", "light.emitter.radiance.value"]   # a BSDF and an emitter: ∂f and ∂E
SCALAR = 1
#: On CUDA, host<->device copies up to this size are not lane data (kernel parameters, one-lane
#: literals, the parameter vector); every lane array of these tests is at least 4 times larger.
COPY_BYTES = 16 << 10


def _problem(mi, rfilter: str = "box"):
    from services.solver.estimators.problem import Problem
    from services.solver.scene.builtin import cornell_box
    from services.solver.scene.load import load_scene
    from services.solver.scene.params import ParameterSet

    d = cornell_box()
    d["sensor"]["film"]["rfilter"] = {"type": rfilter}   # box: per-ray contraction; gaussian: through the film
    scene = load_scene(mitsuba_dict=d, resolution=RESOLUTION)
    return Problem(scene, ParameterSet(scene.params, KEYS))


def _trainer(problem, pooled: bool):
    from schemas.solver import PoolConfig, TrainingConfig
    from services.solver.training.trainer import FieldTrainer

    config = TrainingConfig(residual_points=1024, incident_samples=16,
                            pool=PoolConfig(enabled=pooled, chunks=1, reuse=1))   # every step draws afresh
    return FieldTrainer(problem, config, radiance=True, differential=True, seed=3)


def _device_copies(bytes_over: int):
    """On CUDA: a profiler over the block, and the host<->device copies it saw larger than
    ``bytes_over`` (filled in on exit); a no-op list on the CPU."""
    import contextlib

    from services.solver.backend import device

    copies: list[tuple[str, int]] = []
    if device().kind != "cuda":
        return contextlib.nullcontext(copies)

    @contextlib.contextmanager
    def profiled():
        import json
        import tempfile

        from torch.profiler import ProfilerActivity, profile

        with profile(activities=[ProfilerActivity.CUDA]) as prof:
            yield copies
            torch.cuda.synchronize()
        with tempfile.NamedTemporaryFile(suffix=".json") as trace:
            prof.export_chrome_trace(trace.name)
            events = json.loads(Path(trace.name).read_text()).get("traceEvents", [])
        for event in events:   # kineto's memcpy events carry their size in args.bytes
            name = str(event.get("name", ""))
            if event.get("cat") == "gpu_memcpy" and ("HtoD" in name or "DtoH" in name):
                size = int(event.get("args", {}).get("bytes", -1))
                if size < 0 or size > bytes_over:
                    copies.append((name, size))

    return profiled()


def _check_step(ledger: Ledger, parameters: int) -> None:
    assert not ledger.of("host->torch"), f"host data copied to torch in a training step:\n{ledger}"
    assert not ledger.larger_than("torch->host", SCALAR), f"a tensor read back in a training step:\n{ledger}"
    assert not ledger.larger_than("drjit->host", parameters), f"Dr.Jit lanes read to the host:\n{ledger}"


@pytest.mark.parametrize("pooled", [False, True], ids=["fresh-batches", "pool"])
def test_a_training_step_moves_nothing_but_scalars_through_the_host(mi, pooled):
    problem = _problem(mi)
    trainer = _trainer(problem, pooled)
    trainer.step()                   # the first step calibrates the output scales (read once, logged)
    with _device_copies(bytes_over=COPY_BYTES) as copies, host_transfers() as ledger:
        stats = trainer.step()
    assert np.isfinite(stats.radiance_loss) and np.isfinite(stats.differential_loss)
    assert ledger.of("drjit->host") or ledger.of("torch->host"), "the hook saw nothing: is it installed?"
    _check_step(ledger, problem.parameters.n)
    assert not copies, f"host<->device copies in a training step: {copies}"


def _fields(problem, trainer):
    trainer.train(2)
    return trainer.radiance, trainer.differential


@pytest.mark.parametrize("rfilter", ["box", "gaussian"])
def test_a_field_query_moves_only_its_input_and_its_output(mi, rfilter):
    from services.solver.estimators.first_hits import FirstHitCache

    problem = _problem(mi, rfilter)
    radiance, differential = _fields(problem, _trainer(problem, pooled=True))
    cache = FirstHitCache(problem, [0], 4, seed=4, fields=[radiance, differential])
    width, height = RESOLUTION
    dz_dy = np.random.default_rng(0).normal(size=(height, width, 3))
    image = height * width * 3
    with _device_copies(bytes_over=COPY_BYTES) as copies, host_transfers() as ledger:
        candidate = cache.candidate(0, radiance)
        dz_dp = cache.loss_gradient(0, differential, dz_dy)
    assert candidate.shape == (height, width, 3) and dz_dp.shape == (problem.parameters.n,)
    assert np.all(np.isfinite(dz_dp)) and np.any(dz_dp != 0)
    inputs = ledger.of("host->torch")
    assert [t.size for t in inputs] == [image], f"only dz/dy may be copied to the device:\n{ledger}"
    outputs = ledger.larger_than("torch->host", problem.parameters.n)
    assert [t.size for t in outputs] == [image], f"only the candidate image may be read back:\n{ledger}"
    assert not ledger.larger_than("drjit->host", problem.parameters.n), f"Dr.Jit lanes read to the host:\n{ledger}"
    from services.solver.backend import device

    # on CUDA: the candidate image back (float32) and dz/dy in (float64), nothing else of that size
    assert sorted(size for _, size in copies) == ([image * 4, image * 8] if device().kind == "cuda" else []), copies


def test_the_ndrf_rhs_gradient_moves_only_its_input_and_its_output(mi):
    from services.solver.estimators.methods.base import Fields
    from services.solver.estimators.methods.camera_hit import NdrfRhs

    problem = _problem(mi)
    radiance, differential = _fields(problem, _trainer(problem, pooled=True))
    fields = Fields(radiance, differential)
    method = NdrfRhs()
    width, height = RESOLUTION
    dz_dy = np.random.default_rng(1).normal(size=(height, width, 3))
    method.loss_gradient(problem, fields, dz_dy, spp=1, seed=5)    # compiles the kernels
    with host_transfers() as ledger:
        dz_dp = method.loss_gradient(problem, fields, dz_dy, spp=1, seed=6)
    assert dz_dp.shape == (problem.parameters.n,) and np.all(np.isfinite(dz_dp))
    assert [t.size for t in ledger.of("host->torch")] == [height * width * 3], \
        f"only dz/dy may be copied to the device:\n{ledger}"
    assert not ledger.larger_than("torch->host", problem.parameters.n), f"a tensor read back:\n{ledger}"
    assert not ledger.larger_than("drjit->host", problem.parameters.n), f"Dr.Jit lanes read to the host:\n{ledger}"


def test_a_dlpack_exchange_shares_memory_with_dr_jit(mi):
    """The hand-over itself: the tensor of a ``mi.Float`` views Dr.Jit's buffer (on the CPU the
    pointers can be compared), and the hook counts nothing for it; a numpy route is counted."""
    import drjit as dr

    from services.solver.sampling.tensors import flat, rgb

    x = dr.arange(mi.Float, 1000)
    dr.eval(x)
    with host_transfers() as ledger:
        t = flat(x)
        c = rgb(mi.Color3f(x, 2 * x, 0.5))
    assert not ledger.transfers, str(ledger)
    assert c.shape == (1000, 3) and float(c[10, 1]) == 20.0 and float(c[999, 2]) == 0.5
    if t.device.type == "cpu":
        assert t.data_ptr() == x.torch().data_ptr()
    with host_transfers() as ledger:
        torch.from_numpy(np.array(x))
    assert [(t.kind, t.size) for t in ledger.transfers] == [("drjit->host", 1000), ("host->torch", 1000)]

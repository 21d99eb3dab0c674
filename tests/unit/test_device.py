"""Device selection (services/solver/backend.py): ``NDRF_DEVICE`` and the two probes, faked here in
every combination, then the real probes on this machine."""

from __future__ import annotations

import itertools

import pytest

from services.solver import backend

WHY_MITSUBA = "Dr.Jit's CUDA backend does not start (faked)"
WHY_TORCH = "torch 2.x is a CPU-only build (faked)"


class FakeProbe:
    def __init__(self, why: str | None):
        self.why, self.calls = why, 0

    def __call__(self) -> str | None:
        self.calls += 1
        return self.why


@pytest.mark.parametrize(("mitsuba_ok", "torch_ok"), list(itertools.product([True, False], repeat=2)))
def test_auto_is_cuda_only_when_both_probes_succeed_and_says_why_not(mitsuba_ok, torch_ok):
    mitsuba, torch = FakeProbe(None if mitsuba_ok else WHY_MITSUBA), FakeProbe(None if torch_ok else WHY_TORCH)
    kind, reason = backend.choose("auto", mitsuba, torch)
    assert kind == ("cuda" if mitsuba_ok and torch_ok else "cpu")
    assert (WHY_MITSUBA in reason) == (not mitsuba_ok)
    assert (WHY_TORCH in reason) == (mitsuba_ok and not torch_ok)
    assert mitsuba.calls == 1
    assert torch.calls == (1 if mitsuba_ok else 0)    # no torch import for a machine Mitsuba already ruled out


@pytest.mark.parametrize(("mitsuba_ok", "torch_ok"), list(itertools.product([True, False], repeat=2)))
def test_cpu_probes_nothing(mitsuba_ok, torch_ok):
    mitsuba, torch = FakeProbe(None if mitsuba_ok else WHY_MITSUBA), FakeProbe(None if torch_ok else WHY_TORCH)
    assert backend.choose("cpu", mitsuba, torch) == ("cpu", "NDRF_DEVICE=cpu")
    assert mitsuba.calls == torch.calls == 0


@pytest.mark.parametrize(("mitsuba_ok", "torch_ok"), list(itertools.product([True, False], repeat=2)))
def test_explicit_cuda_is_refused_loudly_naming_every_reason(mitsuba_ok, torch_ok):
    mitsuba, torch = FakeProbe(None if mitsuba_ok else WHY_MITSUBA), FakeProbe(None if torch_ok else WHY_TORCH)
    if mitsuba_ok and torch_ok:
        assert backend.choose("cuda", mitsuba, torch)[0] == "cuda"
        return
    with pytest.raises(backend.DeviceUnavailable) as raised:
        backend.choose("cuda", mitsuba, torch)
    message = str(raised.value)
    assert message.startswith("NDRF_DEVICE=cuda, but ")
    assert (WHY_MITSUBA in message) == (not mitsuba_ok) and (WHY_TORCH in message) == (not torch_ok)
    assert mitsuba.calls == torch.calls == 1      # both asked: the error lists everything to fix


@pytest.mark.parametrize("value", ["gpu", "cuda:1", "llvm"])
def test_an_unknown_device_is_an_error_not_a_fallback(value):
    with pytest.raises(ValueError, match="expected one of auto, cpu, cuda"):
        backend.requested_device({"NDRF_DEVICE": value})
    with pytest.raises(ValueError, match="expected one of auto, cpu, cuda"):
        backend.choose(value, FakeProbe(None), FakeProbe(None))


def test_the_setting_is_read_case_insensitively_and_defaults_to_auto():
    assert backend.requested_device({}) == "auto"
    assert backend.requested_device({"NDRF_DEVICE": ""}) == "auto"
    assert backend.requested_device({"NDRF_DEVICE": " CUDA "}) == "cuda"
    assert backend.requested_device({"NDRF_DEVICE": "cpu"}) == "cpu"


def test_the_device_of_this_process_names_its_variant_and_torch_device(mi):
    """The real probes, once per process: whatever this machine is, the variant Mitsuba runs and the
    device torch creates tensors on are the chosen device's, and the description says why."""
    import torch

    chosen = backend.device()
    assert mi.variant() == backend.VARIANTS[chosen.kind] == chosen.variant
    assert torch.zeros(1).device.type == chosen.kind == backend.torch_device().type
    described = backend.describe_device()
    assert described["device"] == chosen.kind and described["reason"] and described["name"]
    assert described["requested"] == backend.requested_device()


def test_the_service_settings_name_the_device():
    from services.settings import Settings

    assert Settings().device == backend.requested_device()
    assert Settings(device="cpu").device == "cpu"
    with pytest.raises(ValueError):
        Settings(device="gpu")

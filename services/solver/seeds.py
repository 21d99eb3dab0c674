"""Deterministic seeds: every random stream of a job is a pure function of the job's seed and the
position in the computation (phase, iteration, step, pass), so equal seeds give equal runs and a
resumed run draws exactly the samples the uninterrupted one would have drawn."""

from __future__ import annotations

_MASK64 = (1 << 64) - 1


def _mix(x: int) -> int:
    """SplitMix64 finaliser."""
    x = (x + 0x9E3779B97F4A7C15) & _MASK64
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & _MASK64
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & _MASK64
    return x ^ (x >> 31)


def derive_seed(*parts: int | str) -> int:
    """A 32-bit seed from any sequence of integers or short labels (uint32, as Mitsuba wants)."""
    state = 0
    for part in parts:
        value = part if isinstance(part, int) else int.from_bytes(str(part).encode()[:8].ljust(8, b"\0"), "little")
        state = _mix(state ^ (value & _MASK64))
    return state & 0xFFFFFFFF

"""Splitting a sample count into passes of bounded width (the one helper every renderer uses).

A 64x64 image at 4096 spp is 16.7 M paths; Dr.Jit evaluates a pass as one wavefront, so memory
grows with its width. Passes of equal spp with different seeds are averaged.
"""

from __future__ import annotations

#: Lanes (rays or paths) per pass of the path tracers and of the camera-hit methods.
LANES_PER_PASS = 1 << 21


def passes_for(pixels: int, spp: int, lanes_per_pass: int = LANES_PER_PASS) -> tuple[int, int]:
    """``(passes, spp_per_pass)`` with ``passes · spp_per_pass == spp`` and at most
    ``lanes_per_pass`` lanes per pass (at least 1 spp per pass whatever the image size)."""
    if spp < 1:
        raise ValueError(f"spp must be >= 1, got {spp}")
    per_pass = max(1, min(spp, lanes_per_pass // max(1, pixels)))
    while spp % per_pass:
        per_pass -= 1
    return spp // per_pass, per_pass

"""Benchmarks (timings live here, never in unit tests). Run with ``python -m bench.<name>``."""

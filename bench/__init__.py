"""Benchmarks (timings live here, never in unit tests). Run with ``python -m bench.<name>``; one-off investigations with ``python -m bench.investigations.<name>``."""

"""Benchmarks (timings live here, never in unit tests). Run with ``python -m bench.<name>``.

One-off investigations: ``python -m bench.investigations.<name>`` (``bench/investigations/README.md``).
"""

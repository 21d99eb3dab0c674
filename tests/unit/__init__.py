"""Unit tier: in-process tests of the solver, the schemas and the service's logic; no server process
(marked ``unit`` by tests/conftest.py)."""

"""End-to-end tier: real ``ndrf serve``, ``ndrf worker`` and CLI processes, the dashboard in
Chromium, faults injected (marked ``e2e`` by tests/conftest.py)."""

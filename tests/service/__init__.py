"""Service tier: the service's parts against real infrastructure (a throw-away Redis, the folder and
S3 stores, sandboxed child processes; marked ``service`` by tests/conftest.py)."""

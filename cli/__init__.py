"""The ``ndrf`` command line: ``gradient``, ``run``, ``serve``, ``worker``."""

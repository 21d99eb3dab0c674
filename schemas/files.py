"""Names of a job's files that both the service and its clients spell (``ndrf fetch`` asks for them)."""

from __future__ import annotations

import re


def mesh_name(shape: str) -> str:
    """A shape id as a file name, one to one: an XML id may hold '/' or '.', so every character
    outside ``[A-Za-z0-9_-]`` becomes ``~`` and its UTF-8 bytes in hex (``a.b`` -> ``a~2eb``,
    ``a_b`` stays ``a_b``); a plain id never holds ``~``, and ``~`` itself is escaped."""
    return re.sub(r"[^A-Za-z0-9_-]", lambda m: "".join(f"~{b:02x}" for b in m.group(0).encode()), shape) or "~"

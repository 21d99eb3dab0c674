"""Mesh file names (``schemas.files.mesh_name``): one file per shape, whatever its id."""

from __future__ import annotations

import re

from schemas.files import mesh_name


def test_mesh_file_names_are_one_to_one():
    ids = ["a.b", "a_b", "a/b", "a~2eb", "a~b", "ab", "", "é", "a-b"]
    names = [mesh_name(i) for i in ids]
    assert len(set(names)) == len(ids), dict(zip(ids, names))               # two shapes never share a file
    assert mesh_name("a_b") == "a_b" and mesh_name("a.b") == "a~2eb"           # plain ids keep their name
    assert all(re.fullmatch(r"[A-Za-z0-9_~-]+", n) for n in names)             # what the mesh routes accept

"""A view's files (``services.jobs.views``' docstring lists them): written by the sandboxed child
that rendered the view, into a folder of its work folder, and read back by the API from there, by
file, never through the API's memory (issue 38: a 512x512 view's arrays took the API from 87 to
1595 MiB when they came back in frames).

The child writes every file but ``view.json`` (:func:`write_view`), one at a time, and answers
the PNG scales. The API moves that folder out of the child's reach, opens each file without
following links (:func:`open_view`: a hostile child could leave a link to any file the API may
read), sizes it from the open file, and copies at most that many bytes into the store.
"""

from __future__ import annotations

import json
import os
import re
import stat
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from services.store.images import gradient_png, npy_bytes, srgb_png

#: The names a view's files may have.
VIEW_FILE_PATTERN = r"^(radiance\.(npy|png)|gradients\.npy|prb\.npy|(gradient|prb)-\d{1,3}\.png|view\.json)$"
#: Files every view has (the child's folder must hold them).
REQUIRED = ("radiance.npy", "radiance.png", "gradients.npy")


def file_items(radiance: np.ndarray, gradients: np.ndarray, prb: np.ndarray | None,
               scales: dict[int, float]) -> Iterator[tuple[str, bytes]]:
    """Each file of a view but ``view.json``, one at a time; fills ``scales`` (the gradient PNGs'
    scale per scalar, which the prb PNGs share, side by side)."""
    yield "radiance.npy", npy_bytes(radiance.astype(np.float32))
    yield "radiance.png", srgb_png(radiance)
    yield "gradients.npy", npy_bytes(gradients.astype(np.float32))
    for p, image in enumerate(gradients):
        data, scales[p] = gradient_png(image)
        yield f"gradient-{p}.png", data
    if prb is not None:
        yield "prb.npy", npy_bytes(prb.astype(np.float32))
        for p, image in enumerate(prb):
            yield f"prb-{p}.png", gradient_png(image, scales[p] or None)[0]


def view_json(meta: dict, scales: dict) -> bytes:
    return json.dumps({**meta, "scales": scales}, indent=2).encode()


def view_files(radiance: np.ndarray, gradients: np.ndarray, prb: np.ndarray | None, meta: dict) -> dict[str, bytes]:
    """Every file of one view by name, in memory (``ndrf view``, which writes them itself)."""
    scales: dict[int, float] = {}
    files = dict(file_items(radiance, gradients, prb, scales))
    files["view.json"] = view_json(meta, scales)
    return files


def write_view(folder: Path, radiance: np.ndarray, gradients: np.ndarray, prb: np.ndarray | None) -> dict:
    """In the child: write the view's files but ``view.json`` into ``folder`` (created); returns
    ``{"scales": ...}`` for its answer."""
    folder.mkdir()
    scales: dict[int, float] = {}
    for name, data in file_items(radiance, gradients, prb, scales):
        (folder / name).write_bytes(data)
    return {"scales": scales}


@dataclass
class OpenView:
    """The files of a view a child wrote, open: by name, the file and its size."""

    files: dict[str, tuple[BinaryIO, int]]

    @property
    def total(self) -> int:
        return sum(size for _, size in self.files.values())

    def read(self, name: str, most: int) -> bytes:
        handle, size = self.files[name]
        if size > most:
            raise ValueError(f"{name} is {size} bytes, over {most}")
        return handle.read(size)

    def close(self) -> None:
        for handle, _ in self.files.values():
            handle.close()


def open_view(folder: Path) -> OpenView:
    """Open the files of the view in ``folder`` (no link followed, regular files only, known names
    only); ``ValueError`` naming what is wrong."""
    flags = os.O_RDONLY | os.O_NOFOLLOW | getattr(os, "O_CLOEXEC", 0)
    try:
        dir_fd = os.open(folder, flags | os.O_DIRECTORY)
    except OSError as exc:
        raise ValueError(f"the view child wrote no folder of files ({exc.strerror})") from None
    opened = OpenView({})
    try:
        for name in sorted(os.listdir(dir_fd)):
            if not re.match(VIEW_FILE_PATTERN, name) or name == "view.json":
                raise ValueError(f"the view child wrote an unexpected file {name[:80]!r}")
            fd = os.open(name, flags, dir_fd=dir_fd)
            info = os.fstat(fd)
            handle = os.fdopen(fd, "rb")
            if not stat.S_ISREG(info.st_mode):
                handle.close()
                raise ValueError(f"the view child's {name} is not a file")
            opened.files[name] = (handle, info.st_size)
        missing = [name for name in REQUIRED if name not in opened.files]
        if missing:
            raise ValueError(f"the view child wrote no {', '.join(missing)}")
    except OSError as exc:
        opened.close()
        raise ValueError(f"the view child's files could not be read ({exc.strerror})") from None
    except BaseException:
        opened.close()
        raise
    finally:
        os.close(dir_fd)
    return opened

"""File names of an uploaded scene: what a path inside the scene folder may be, and the
decoding of a file's base64 (:mod:`services.uploads.scene` applies them; ``pack_scene`` too)."""

from __future__ import annotations

import base64
import binascii
import re

from schemas.errors import InvalidJob

MAIN_XML_NAME = "scene.xml"  # where services.solver.scene.load.write_scene_files writes the document
RESERVED_FOLDERS = ("plugins", "data")  # Mitsuba finds its plugins and data via the file resolver
MAX_PATH_CHARS = 255
MAX_NAME_BYTES = 255  # NAME_MAX: UTF-8 bytes of one file or folder name
MAX_PATH_BYTES = 4096  # PATH_MAX

_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def path_problem(path: str, what: str) -> str | None:
    """Why ``path`` is not a plain relative POSIX path inside the scene folder, or None."""
    parts = path.split("/")
    if not path or len(path) > MAX_PATH_CHARS:
        return f"{what} {path[:MAX_PATH_CHARS]!r} must have 1 to {MAX_PATH_CHARS} characters"
    if "$" in path:
        return f"{what} {path!r}: substitution ($) is not allowed in file names"
    if _CONTROL.search(path):
        return f"{what} {path!r} must not contain control characters"
    if "\\" in path or re.match(r"[A-Za-z]:", path):
        return f"{what} {path!r} must use '/' separators (no backslashes, no drive letters)"
    if path.startswith("/"):
        return f"{what} {path!r} must be relative to the scene (no leading '/')"
    if ".." in parts:
        return f"{what} {path!r} must stay inside the scene folder (no '..')"
    if "" in parts or "." in parts:
        return f"{what} {path!r} must be normalized (no '//', './' or trailing '/')"
    if parts[0].startswith("~"):
        return f"{what} {path!r} must not start with '~'"
    try:
        size = len(path.encode("utf-8"))
    except UnicodeEncodeError:
        return f"{what} {path!r} is not valid Unicode (it contains a lone surrogate)"
    for part in parts:
        if len(part.encode("utf-8")) > MAX_NAME_BYTES:
            return (f"{what} {short(path)}: the name {short(part)} has {len(part.encode('utf-8'))} bytes in UTF-8; "
                    f"at most {MAX_NAME_BYTES} bytes are allowed per file or folder name")
    if size > MAX_PATH_BYTES:
        return f"{what} {short(path)} has {size} bytes in UTF-8; at most {MAX_PATH_BYTES} are allowed"
    return None


def short(text: str, keep: int = 40) -> str:
    return repr(text) if len(text) <= keep else repr(text[:keep]) + f"... ({len(text)} characters)"


def reserved_problem(path: str) -> str | None:
    if path == MAIN_XML_NAME:
        return f"{MAIN_XML_NAME!r} is reserved for the main document"
    if "/" in path and path.split("/")[0] in RESERVED_FOLDERS:
        return f"the top-level folders {', '.join(RESERVED_FOLDERS)} are reserved for Mitsuba's plugins and data"
    return None


def decode_base64(value: str, field: str, max_bytes: int) -> bytes:
    if len(value) > 4 * ((max_bytes + 2) // 3):
        raise InvalidJob(field, f"decodes to more than {max_bytes} bytes, the limit per file")
    try:
        data = base64.b64decode(value, validate=True)
    except (binascii.Error, ValueError) as exc:
        raise InvalidJob(field, f"is not valid base64 (standard alphabet, padded, no whitespace): {exc}") from None
    if len(data) > max_bytes:
        raise InvalidJob(field, f"decodes to {len(data)} bytes, more than {max_bytes}, the limit per file")
    return data

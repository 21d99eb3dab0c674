"""Resolve a scene's own ``<default>`` substitutions in file names, before the upload checks.

Mitsuba replaces ``$name`` in attribute values with the value of the scene's ``<default
name="name" value="..."/>``. The upload checks (:mod:`services.uploads.scene`) refuse ``$`` in
file names, since a substitution applied after the check could name any file. Scenes written for
Mitsuba use it for textures (``<default name="tex" value="albedo.exr"/>`` ... ``value="$tex"``), so
:func:`resolve_file_defaults` applies the document's own top-level defaults to its file names
first; the checks then see, and the worker writes, the resolved document: what Mitsuba reads has no
substitution left in any file name, so the check and the load agree by construction.

Rules, each loud when broken (an :class:`InvalidJob` naming the field):

* only ``<default>`` elements directly under ``<scene>`` count, with names of letters, digits and
  ``_``, no ``$`` in their values, and no name that is a prefix of another (Mitsuba's textual
  replacement and a token match would then differ);
* ``$name`` in a file name (a ``filename`` attribute or a ``<... name="filename" value>``) is
  replaced when ``name`` is a default; anything else is left, and refused by the checks as before;
* a document without a substitution in a file name is returned unchanged (text for text); in one
  with, a default that no attribute uses any more is dropped (so that a default naming a file in a
  folder is not refused for defining a substitution with a ``/``).
"""

from __future__ import annotations

import re
from xml.etree.ElementTree import Element, tostring

from schemas.errors import InvalidJob

_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_USE = re.compile(r"\$([A-Za-z_][A-Za-z0-9_]*)")


def scene_defaults(root: Element, field: str) -> dict[str, str]:
    """``{name: value}`` of the top-level ``<default>`` elements of a parsed scene."""
    defaults: dict[str, str] = {}
    for element in root:
        if element.tag != "default":
            continue
        name, value = element.get("name", ""), element.get("value", "")
        if not _NAME.fullmatch(name):
            raise InvalidJob(field, f"<default name={name!r}>: a default's name must be letters, digits and '_'")
        if "$" in value:
            raise InvalidJob(field, f"<default name={name!r}>: a default's value must not use another substitution")
        defaults[name] = value
    for name in defaults:
        longer = [other for other in defaults if other != name and other.startswith(name)]
        if longer:
            raise InvalidJob(field, f"<default name={name!r}> is a prefix of {longer[0]!r}: ambiguous substitution")
    return defaults


def _substitute(value: str, defaults: dict[str, str]) -> str:
    return _USE.sub(lambda m: defaults.get(m.group(1), m.group(0)), value)


def resolve_file_defaults(root: Element, text: str, field: str) -> str:
    """``text`` (the document ``root`` was parsed from) with the scene's defaults applied to its
    file names; ``text`` itself when no file name uses one."""
    defaults = scene_defaults(root, field) if any(e.tag == "default" for e in root) else {}
    if not defaults:
        return text
    changed = False
    for element in root.iter():
        attributes = ["filename"] if "filename" in element.attrib else []
        if element.get("name") == "filename" and "value" in element.attrib:
            attributes.append("value")
        for attribute in attributes:
            value = element.attrib[attribute]
            resolved = _substitute(value, defaults)
            if resolved != value:
                element.set(attribute, resolved)
                changed = True
    if not changed:
        return text
    # A default now used by no attribute is dropped: one naming a file in a folder ('textures/a.exr')
    # would otherwise be refused for defining a substitution with a '/'
    used = {m.group(1) for e in root.iter() for v in e.attrib.values() for m in _USE.finditer(v)}
    for element in [e for e in root if e.tag == "default" and e.get("name") not in used]:
        root.remove(element)
    return tostring(root, encoding="unicode")

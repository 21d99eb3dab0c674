"""Human-readable validation errors: one line per problem, naming the field and what is allowed."""

from __future__ import annotations

from pydantic import ValidationError


def field_path(loc: tuple) -> str:
    """``('parameters', 0, 'init')`` -> ``parameters[0].init`` (union branch names are dropped)."""
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        elif part[:1].isupper() or part.startswith("function-") or "[" in part:
            continue  # pydantic's names of union members / validators, not user fields
        else:
            out += f".{part}" if out else part
    return out or "(root)"


def describe(exc: ValidationError) -> list[tuple[str, str]]:
    """``[(field, message)]`` for every error of a pydantic validation failure."""
    seen, out = set(), []
    for err in exc.errors(include_url=False):
        item = (field_path(tuple(err["loc"])), err["msg"])
        if item not in seen:
            seen.add(item)
            out.append(item)
    return out

"""From an experiment spec to its runs: field paths, the grid x random draws x seeds product.

Pure logic over JSON documents (no store, no scene). A run is its ``values``: field path -> value
of every varied field, the seed included; its identity (``key``) is their canonical JSON, so
appending runs recomputes the product and adds only the keys that are new. Random draws are
seeded per (``random_seed``, sample, path): draw ``s`` is the same however many samples follow,
so adding samples keeps the earlier ones.
"""

from __future__ import annotations

import copy
import hashlib
import itertools
import json
import math
import random
import re
from dataclasses import dataclass
from typing import Any

from schemas.experiments import RandomChoice, RandomRange

SEED = "seed"
_SEGMENT = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)((?:\[[^\[\]]+\])*)")
_BRACKET = re.compile(r"\[([^\[\]]+)\]")


class InvalidExperiment(ValueError):
    """An experiment that cannot be queued: ``field`` is the JSON path (``grid.learning_rate``,
    ``runs[3].learning_rate``), ``message`` says what is wrong. The API answers a 422."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field, self.message = field, message


# ------------------------------------------------------------------------------ field paths

def parse_path(path: str) -> list[str | int]:
    """``parameters[red.reflectance.value].init`` -> ``['parameters', 'red.reflectance.value', 'init']``;
    ``render.resolution`` -> ``['render', 'resolution']``; integers in brackets are indices."""
    parts: list[str | int] = []
    rest = path
    while rest:
        match = _SEGMENT.match(rest)
        if match is None:
            raise ValueError(f"{path!r} is not a field path ({rest!r} is not a field name)")
        parts.append(match.group(1))
        for inner in _BRACKET.findall(match.group(2)):
            parts.append(int(inner) if inner.isdigit() else inner)
        rest = rest[match.end():]
        if rest.startswith("."):
            rest = rest[1:]
            if not rest:
                raise ValueError(f"{path!r} ends with '.'")
        elif rest:
            raise ValueError(f"{path!r} is not a field path (unexpected {rest[0]!r})")
    if not parts:
        raise ValueError("empty field path")
    return parts


def _step(node: Any, part: str | int, path: str) -> tuple[Any, str | int]:
    """The container key of ``part`` in ``node`` (a list of objects is addressed by their 'key' too)."""
    if isinstance(node, dict):
        if part not in node:
            raise KeyError(f"{path!r}: the job has no field {part!r} here (fields: {', '.join(map(str, node))})")
        return node[part], part
    if isinstance(node, list):
        if isinstance(part, int):
            if part >= len(node):
                raise KeyError(f"{path!r}: index {part} is out of range (the list has {len(node)} entries)")
            return node[part], part
        for i, item in enumerate(node):
            if isinstance(item, dict) and item.get("key") == part:
                return item, i
        keys = [item.get("key") for item in node if isinstance(item, dict)]
        raise KeyError(f"{path!r}: no entry with key {part!r} (keys: {keys})")
    raise KeyError(f"{path!r}: {part!r} addresses inside a value that is not an object or a list")


def get_path(document: Any, path: str) -> Any:
    node = document
    for part in parse_path(path):
        node, _ = _step(node, part, path)
    return node


def set_path(document: dict, path: str, value: Any) -> None:
    """Set an existing field (every path must name a field of the base job, defaults included)."""
    parts = parse_path(path)
    node: Any = document
    for part in parts[:-1]:
        node, _ = _step(node, part, path)
    _, key = _step(node, parts[-1], path)
    node[key] = copy.deepcopy(value)


# -------------------------------------------------------------------------------- expansion

@dataclass(frozen=True)
class PlannedRun:
    key: str
    values: dict[str, Any]


def run_key(values: dict[str, Any]) -> str:
    return json.dumps(values, sort_keys=True, separators=(",", ":"))


def _seeds(sweep: dict, base: dict) -> list[int]:
    return list(sweep.get("seeds") or [base.get("seed", 0)])


def count_runs(sweep: dict, base: dict) -> int:
    grid = sweep.get("grid") or {}
    samples = sweep.get("samples", 1) if sweep.get("random") else 1
    return math.prod(len(v) for v in grid.values()) * samples * len(_seeds(sweep, base))


def draw(spec: RandomRange | RandomChoice, random_seed: int, sample: int, path: str) -> Any:
    digest = hashlib.sha256(f"{random_seed}/{sample}/{path}".encode()).digest()
    rng = random.Random(int.from_bytes(digest[:8], "big"))
    if isinstance(spec, RandomChoice):
        return copy.deepcopy(spec.values[rng.randrange(len(spec.values))])
    if spec.log:
        value = math.exp(rng.uniform(math.log(spec.min), math.log(spec.max)))
    else:
        value = rng.uniform(spec.min, spec.max)
    value = min(max(value, spec.min), spec.max)
    return int(round(value)) if spec.integer else float(f"{value:.6g}")


def check_sweep(sweep: dict, base: dict) -> list[str]:
    """The varied field paths after checking that each names a field of the base job;
    :class:`InvalidExperiment` otherwise."""
    grid, rand = sweep.get("grid") or {}, sweep.get("random") or {}
    for where, paths in (("grid", grid), ("random", rand)):
        for path in paths:
            try:
                get_path(base, path)
            except (ValueError, KeyError) as exc:
                raise InvalidExperiment(f"{where}.{path}", str(exc.args[0])) from None
            if path == SEED:
                raise InvalidExperiment(f"{where}.seed", "vary the seed with 'seeds': [...]")
    both = set(grid) & set(rand)
    if both:
        raise InvalidExperiment(f"random.{sorted(both)[0]}", "a field is either in the grid or random, not both")
    if sweep.get("samples", 1) > 1 and not rand:
        raise InvalidExperiment("samples", "samples > 1 needs at least one 'random' field")
    varied = [p for p in grid if len(grid[p]) > 1] + [p for p in rand if sweep.get("samples", 1) > 1]
    if len(_seeds(sweep, base)) > 1:
        varied.append(SEED)
    return varied


def expand(sweep: dict, base: dict) -> list[PlannedRun]:
    """Every run of ``sweep`` over ``base``, in order: grid combinations (in the order the grid
    names its fields and values), then random samples, then seeds."""
    grid = sweep.get("grid") or {}
    rand = {path: spec if isinstance(spec, (RandomRange, RandomChoice)) else _random_spec(spec)
            for path, spec in (sweep.get("random") or {}).items()}
    samples = sweep.get("samples", 1) if rand else 1
    seed_of_draws = sweep.get("random_seed", 0)
    runs, seen = [], set()
    for combination in itertools.product(*grid.values()):
        fixed = dict(zip(grid, combination))
        for sample in range(samples):
            drawn = {path: _draw_checked(spec, seed_of_draws, sample, path) for path, spec in rand.items()}
            for seed in _seeds(sweep, base):
                values = {**fixed, **drawn, SEED: seed}
                key = run_key(values)
                if key not in seen:          # equal grid values give one run, not two
                    seen.add(key)
                    runs.append(PlannedRun(key, values))
    return runs


def _draw_checked(spec: RandomRange | RandomChoice, random_seed: int, sample: int, path: str) -> Any:
    try:
        value = draw(spec, random_seed, sample, path)
    except (OverflowError, ValueError):
        value = math.inf
    if isinstance(value, float) and not math.isfinite(value):
        raise InvalidExperiment(f"random.{path}", "the range is too wide to draw a finite number from")
    return value


def _random_spec(raw: dict) -> RandomRange | RandomChoice:
    return RandomChoice.model_validate(raw) if "values" in raw else RandomRange.model_validate(raw)


def job_document(base: dict, values: dict[str, Any]) -> dict:
    """The base job with a run's values set (a JSON document, validated by the caller)."""
    document = copy.deepcopy(base)
    for path, value in values.items():
        set_path(document, path, value)
    return document


def merge(sweep: dict, more: dict) -> dict:
    """``sweep`` extended by an append request (grid values, seeds, samples)."""
    merged = copy.deepcopy(sweep)
    grid = merged.setdefault("grid", {})
    for path, values in (more.get("grid") or {}).items():
        if path not in grid:
            raise InvalidExperiment(f"grid.{path}", f"{path!r} is not a grid field of this experiment (its grid "
                                                    f"fields: {sorted(grid)}); an append adds values, not fields")
        grid[path] = grid[path] + [v for v in values if v not in grid[path]]
    if more.get("seeds"):
        current = list(merged.get("seeds") or [])
        if not current:
            raise InvalidExperiment("seeds", "this experiment runs the base job's seed only; it has no seed list "
                                             "to extend")
        merged["seeds"] = current + [s for s in more["seeds"] if s not in current]
    if more.get("samples"):
        if not merged.get("random"):
            raise InvalidExperiment("samples", "this experiment has no random fields")
        merged["samples"] = merged.get("samples", 1) + more["samples"]
    return merged

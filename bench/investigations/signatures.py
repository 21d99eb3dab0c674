"""How many arguments the loop's functions take (issue 45: ``(prepared, recipe, built, state)``
travelled through 10 signatures).

    python -m bench.investigations.signatures [--at COMMIT]

Counts every function's parameters (``self`` and ``cls`` left out) in the modules of the loop,
read from the working tree or, with ``--at``, from a commit (``git show``), and the signatures
that carry the four objects of a run one by one.
"""

from __future__ import annotations

import argparse
import ast
import logging
import subprocess
from pathlib import Path

log = logging.getLogger("bench.investigations.signatures")
ROOT = Path(__file__).resolve().parents[2]
MODULES = ("loop", "state", "remeshing", "estimate", "build", "run", "plan")
CARRIED = "prepared: Prepared, recipe: Recipe, built: Built"


def source(module: str, at: str | None) -> str | None:
    path = f"services/solver/optimize/{module}.py"
    if at is None:
        file = ROOT / path
        return file.read_text() if file.exists() else None
    shown = subprocess.run(["git", "show", f"{at}:{path}"], cwd=ROOT, capture_output=True, text=True)
    return shown.stdout if shown.returncode == 0 else None


def counts(text: str) -> list[tuple[str, int]]:
    """``(function, arguments)`` of every function in ``text``."""
    out = []
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, ast.FunctionDef):
            a = node.args
            n = len(a.posonlyargs) + len(a.args) + len(a.kwonlyargs)
            n -= 1 if a.args and a.args[0].arg in ("self", "cls") else 0
            out.append((node.name, n))
    return out


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(prog="python -m bench.investigations.signatures", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--at", default=None, help="a commit (default: the working tree)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    rows, carried = [], 0
    for module in MODULES:
        text = source(module, args.at)
        if text is None:
            continue
        carried += text.count(CARRIED)
        rows += [(f"{module}.{name}", n) for name, n in counts(text)]
    total = sum(n for _, n in rows)
    widest = max(rows, key=lambda row: row[1])
    log.info("%d functions, %d arguments (mean %.2f), most %d (%s); %d signatures carry (prepared, recipe, "
             "built, ...)", len(rows), total, total / len(rows), widest[1], widest[0], carried)


if __name__ == "__main__":
    main()

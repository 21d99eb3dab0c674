"""Helpers shared by the CLI commands: logging, reading job files with readable errors."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import click
from pydantic import ValidationError

from schemas.job import JobSpec
from schemas.validation import describe


def setup_logging(verbose: int) -> None:
    level = logging.WARNING if verbose == 0 else logging.INFO if verbose == 1 else logging.DEBUG
    logging.basicConfig(level=level, format="%(asctime)s %(levelname)s %(name)s: %(message)s")


def read_job(path: str | Path) -> JobSpec:
    """Parse and validate a job file; a bad file raises ``click.ClickException`` listing every
    offending field and what is allowed, before anything is loaded or rendered."""
    path = Path(path)
    try:
        raw = json.loads(path.read_bytes().decode("utf-8"))
    except UnicodeDecodeError as exc:
        raise click.ClickException(f"{path}: not UTF-8 text (byte {exc.start}): a job file is JSON") from None
    except json.JSONDecodeError as exc:
        raise click.ClickException(f"{path}: not valid JSON: {exc}") from None
    except OSError as exc:
        raise click.ClickException(f"{path}: cannot read: {exc.strerror}") from None
    try:
        return JobSpec.model_validate(raw)
    except ValidationError as exc:
        lines = "\n".join(f"  {field}: {msg}" for field, msg in describe(exc))
        raise click.ClickException(f"{path}: invalid job file\n{lines}") from None

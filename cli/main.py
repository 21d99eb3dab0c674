"""Entry point of the ``ndrf`` console script."""

from __future__ import annotations

import click

from cli.common import setup_logging
from cli.experiment import compare_command, experiment_command
from cli.gradient import gradient_command
from cli.remote import fetch_command, ls_command, submit_command, watch_command
from cli.run import run_command
from cli.service import serve_command, worker_command
from cli.view import view_command


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.option("-v", "--verbose", count=True, help="More logging (-v info, -vv debug).")
@click.version_option(package_name="ndrf")  # pyproject.toml's version, as installed
def main(verbose: int) -> None:
    """Inverse rendering with Neural Differential Radiance Fields."""
    setup_logging(verbose)


main.add_command(gradient_command)
main.add_command(run_command)
main.add_command(serve_command)
main.add_command(worker_command)
for command in (experiment_command, compare_command, submit_command, watch_command, fetch_command, ls_command,
                view_command):
    main.add_command(command)

if __name__ == "__main__":
    main()

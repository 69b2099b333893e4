"""The `dualhuman` command group, and the consoles every command prints to."""

from __future__ import annotations

import sys

import click
from rich.console import Console

console = Console()
err_console = Console(stderr=True)


class _Group(click.Group):
    """Turns the toolkit's own errors into `error: ... / fix: ...` and exit status 2."""

    def invoke(self, ctx):
        from dualhuman_builder.errors import DualhumanError

        try:
            return super().invoke(ctx)
        except DualhumanError as e:
            from dualhuman_builder.cli.console import print_error

            print_error(err_console, e)
            sys.exit(2)


def _version() -> str:
    from dualhuman_builder import __version__

    return __version__


@click.group(cls=_Group, context_settings={"help_option_names": ["-h", "--help"], "max_content_width": 100})
@click.version_option(package_name="dualhuman-builder", prog_name="dualhuman")
def main():
    """Build datasets of two people in close interaction.

    A workspace (`dualhuman init WS`) holds a catalog of actors, rigs, takes and sequences and
    the artifacts of every stage. Start with `dualhuman doctor` to see what works on this
    machine, and `dualhuman demo` to run the pipeline on simulated actors.
    """

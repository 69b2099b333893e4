"""`dualhuman body`: the anny body model's cache and facts."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main


@main.group()
def body():
    """The anny body model: build its cache, inspect its mesh, bones, mapping and regions."""


@body.command()
@click.option("--check", is_flag=True, help="Only check: exit 1 if the cache is not built, build nothing.")
def warm(check: bool):
    """Build anny's model cache (~790 MB under ~/.cache/anny or $ANNY_CACHE_DIR; a few minutes,
    once per machine) so that loading the body model afterwards takes under a second."""
    from dualhuman_builder.body.model import anny_cache_dir, anny_cache_is_warm

    if check:
        ok = anny_cache_is_warm()
        console.print(f"anny cache {'is built' if ok else 'is not built'} in {anny_cache_dir()}")
        sys.exit(0 if ok else 1)
    from dualhuman_builder.body.info import warm_cache

    with console.status("building the anny cache (a few minutes, once per machine)..."):
        r = warm_cache()
    verb = "built" if r["built"] else "already built; loaded"
    console.print(f"anny cache {verb} in {r['seconds']:.1f} s: {r['cache_dir']} ({r['cache_mb']:.0f} MB)")


@body.command()
@click.option("--bones", is_flag=True, help="List all anny bones.")
@click.option("--mapping", is_flag=True, help="Show the MVN segment mapping and its T-pose deviations.")
@click.option("--regions", is_flag=True, help="Show the body-part regions and their vertex counts.")
@click.option("--mapping-file", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="Check this segment mapping instead of rigs/mvn_anny.toml.")
def info(bones: bool, mapping: bool, regions: bool, mapping_file: Path | None):
    """Describe the body model: mesh size, watertightness and components, bones, shape
    parameters, the MVN segment mapping and the body-part regions."""
    from dualhuman_builder.body.info import body_info
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.cli.console import body_info_tables

    for table in body_info_tables(body_info(get_body_model(), mapping_file), bones, mapping, regions):
        console.print(table)

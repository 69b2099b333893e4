"""`dualhuman body`: the anny body model's facts, and the caches it and the kernels need."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, err_console, main


@main.group()
def body():
    """The anny body model: build this machine's caches, inspect its mesh, bones, mapping and regions."""


@body.command()
@click.option("--check", is_flag=True,
              help="Only check: say whether both caches are built, exit status 1 if one is not; build nothing.")
def warm(check: bool):
    """Build this machine's two caches, once (slow; scripts/setup.sh runs this).

    anny's model cache: about 800 MB under ~/.cache/anny (or $ANNY_CACHE_DIR); the body model
    then loads at once.

    warp's kernel cache: the pipeline's CPU kernels (anny's skinning, the contact queries, the
    scenes' signed distances, the fit's collision and skinning terms) compiled under
    ~/.cache/warp/<warp version> (or $WARP_CACHE_PATH/<warp version>); no stage then compiles
    kernels on its first run. A kernel cache built from other sources of those kernels (another
    version of the toolkit, warp or anny) counts as not built.

    Run again, it loads both and builds nothing.

    \b
    Examples:
      dualhuman body warm
      dualhuman body warm --check
    """
    from dualhuman_builder.body.model import anny_cache_dir, anny_cache_is_warm
    from dualhuman_builder.kernel_cache import kernel_cache_status

    if check:
        anny_ok = anny_cache_is_warm()
        console.print(f"anny cache {'is built' if anny_ok else 'is not built'} in {anny_cache_dir()}", highlight=False)
        kernels = kernel_cache_status()
        console.print(f"warp kernel cache {'is built' if kernels['built'] else 'is not built'} in "
                      f"{kernels['cache_dir']} ({kernels['detail']})", highlight=False, soft_wrap=True)  # fmt: skip
        sys.exit(0 if anny_ok and kernels["built"] else 1)
    from dualhuman_builder.body.info import warm_cache
    from dualhuman_builder.kernel_cache import build_kernel_cache

    with console.status("building the anny cache (once per machine)..."):
        r = warm_cache()
    verb = "built" if r["built"] else "already built; loaded"
    console.print(f"anny cache {verb} in {r['seconds']:.1f} s: {r['cache_dir']} ({r['cache_mb']:.0f} MB)", highlight=False)
    with console.status("compiling warp's kernels (once per machine)...") as spinner:
        k = build_kernel_cache(log=lambda what: spinner.update(f"compiling warp's kernels: {what}..."))
    verb = "built" if k["built"] else "already built; loaded"
    console.print(f"warp kernel cache {verb} in {k['seconds']:.1f} s: {k['cache_dir']} ({len(k['modules'])} modules)",
                  highlight=False, soft_wrap=True)  # fmt: skip
    if k["missing"]:
        err_console.print(f"[yellow]not compiled:[/] {', '.join(k['missing'])} (their kernels are defined only when "
                          "the code runs; they compile on first use)", highlight=False, soft_wrap=True)  # fmt: skip


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

"""`dualhuman`: the command line. Wiring only — every command calls a library function that can
be used from Python as well. Heavy imports happen inside commands so that `--help` is instant."""

from __future__ import annotations

import json
import sys
from pathlib import Path

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
            from dualhuman_builder.console import print_error

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


# ---------------------------------------------------------------------------------------------
@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
def init(workspace: Path):
    """Create a workspace folder WORKSPACE with an empty catalog (or reuse the one there).

    The catalog is WORKSPACE/catalog.sqlite (SQLite, WAL mode); takes go under takes/ and
    stage outputs under artifacts/<take>/<sequence>/<stage>/.
    """
    from dualhuman_builder.workspace import Workspace

    existed = (workspace / "catalog.sqlite").exists()
    with Workspace.init(workspace) as ws:
        console.print(f"{'reusing' if existed else 'created'} workspace {ws.root} (catalog {ws.catalog_path})")


@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
@click.option("--verify", is_flag=True, help="Also re-hash every artifact and take file against the catalog.")
@click.option("--json", "as_json", is_flag=True, help="Print the table as JSON.")
def status(workspace: Path, verify: bool, as_json: bool):
    """Show takes and sequences x pipeline stages: done, failed, running or interrupted, with
    each run's parameters hash. Read-only: works on a workspace you cannot write to."""
    from dualhuman_builder.console import status_table
    from dualhuman_builder.workspace import STAGES, Workspace

    with Workspace.open(workspace, readonly=True) as ws:
        rows = ws.status_rows()
        problems = ws.verify() if verify else []
        if as_json:
            click.echo(json.dumps({"rows": rows, "problems": problems}, indent=2))
        else:
            console.print(status_table(rows, STAGES, f"workspace {ws.root}"))
            if not rows:
                console.print("[dim]no takes yet[/]")
            if verify:
                for p in problems:
                    console.print(f"[red]problem:[/] {p}")
                console.print("[green]all artifacts match the catalog[/]" if not problems else f"{len(problems)} problem(s)")
    if problems:
        sys.exit(1)


@main.command()
@click.option("--json", "as_json", is_flag=True, help="Print the checks as JSON.")
@click.option("--no-render", is_flag=True, help="Skip the Mitsuba test renders (they take a few seconds each).")
def doctor(as_json: bool, no_render: bool):
    """Check what works on this machine, and say how to fix what does not.

    Checks Python and package versions, torch and CUDA, the anny body-model cache, each
    Mitsuba variant actually rendering a tiny scene (scalar, LLVM with the libLLVM it used, CUDA),
    libigl, warp, SQLite, and which capture backends can open (UDP, serial ports, CAN, USB).
    Exit status 1 when a required piece is missing.
    """
    from dualhuman_builder import doctor as doc

    if as_json:
        checks = doc.run_checks(render=not no_render)
        click.echo(doc.checks_to_json(checks))
    else:
        with console.status("checking...") as spinner:
            checks = doc.run_checks(render=not no_render, progress=lambda name: spinner.update(f"checking {name}..."))
        doc.print_report(checks, console)
    sys.exit(doc.exit_code(checks))


@main.command()
@click.argument("workspace", required=False, default="demo-workspace", type=click.Path(file_okay=False, path_type=Path))
def demo(workspace: Path):
    """Run the whole pipeline that exists so far on simulated actors, into WORKSPACE
    (default ./demo-workspace; created if missing, reused if present — a second run only checks
    that everything is up to date). Ends by printing where the outputs are."""
    from dualhuman_builder.console import status_table
    from dualhuman_builder.demo import run_demo
    from dualhuman_builder.workspace import STAGES, Workspace

    result = run_demo(workspace, log=lambda msg: console.print(f"[dim]demo:[/] {msg}", highlight=False))
    with Workspace.open(workspace, readonly=True) as ws:
        console.print(status_table(ws.status_rows(), STAGES, f"workspace {ws.root}"))
    console.print(f"demo finished in {result.seconds:.1f} s; its outputs:")
    for name, path in sorted(result.outputs.items()):
        console.print(f"  {path}", highlight=False, soft_wrap=True)
    console.print("look at preview.png first; preview.glb opens in any glTF viewer (Blender, MeshLab, a browser)",
                  highlight=False, soft_wrap=True)  # fmt: skip


# ---------------------------------------------------------------------------------------------
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
    from dualhuman_builder.console import body_info_tables

    for table in body_info_tables(body_info(get_body_model(), mapping_file), bones, mapping, regions):
        console.print(table)


# ---------------------------------------------------------------------------------------------
@main.group()
def actor():
    """Actors in a workspace: stature, gender and anny shape."""


@actor.command("add")
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
@click.argument("name")
@click.option("--height", type=float, required=True, help="Standing height in metres (e.g. 1.74).")
@click.option("--gender", type=click.Choice(["female", "male", "neutral"]), default="neutral", show_default=True)
@click.option("--no-shape", is_flag=True, help="Do not solve an anny shape from the height now.")
def actor_add(workspace: Path, name: str, height: float, gender: str, no_shape: bool):
    """Register actor NAME (or update them). Unless --no-shape, their anny shape is solved from
    the height (adult age, average build) until a calibration stage refines it."""
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        shape = None
        if not no_shape:
            from dualhuman_builder.body.model import get_body_model
            from dualhuman_builder.body.shape import shape_for_stature

            shape = shape_for_stature(get_body_model(), height, gender)
        a = ws.add_actor(name, height, gender, shape=shape, shape_source=None if no_shape else "stature")
    shape_text = "not solved" if a.shape is None else " ".join(f"{k}={v:.3f}" for k, v in a.shape.items())
    console.print(f"actor {a.name}: {a.height_m:.3f} m, {a.gender}, anny shape {shape_text}", highlight=False)


@actor.command("list")
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
def actor_list(workspace: Path):
    """List the actors of a workspace."""
    from rich.table import Table

    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace, readonly=True) as ws:
        t = Table(title="actors", title_justify="left")
        for c in ("name", "height (m)", "gender", "shape", "shape from"):
            t.add_column(c)
        for a in ws.actors():
            shape = "" if a.shape is None else " ".join(f"{k}={v:.2f}" for k, v in a.shape.items())
            t.add_row(a.name, f"{a.height_m:.3f}" if a.height_m else "", a.gender or "", shape, a.shape_source or "")
        console.print(t)


# ---------------------------------------------------------------------------------------------
@main.group()
def rig():
    """Rig files: sources by URL, actors, character IDs and tracker placement (rigs/*.toml)."""


@rig.command("check")
@click.argument("rig_file", type=click.Path(dir_okay=False, path_type=Path))
def rig_check(rig_file: Path):
    """Check RIG_FILE: sources, actors, MVN character IDs, tracker segments, and its segment
    mapping's bones. Prints a summary, or the first problem with its fix (exit status 2)."""
    from dualhuman_builder.rig import load_rig

    r = load_rig(rig_file)
    console.print(f"rig {r.name!r} is valid: {len(r.sources)} sources, {len(r.actors)} actors, "
                  f"mapping {r.mapping.path.name}")  # fmt: skip
    for s in r.sources:
        console.print(f"  source {s.name}: {s.url}", highlight=False)
    for a in r.actors:
        console.print(f"  actor {a.name}: source {a.source}, character {a.character}, {len(a.trackers)} trackers",
                      highlight=False)  # fmt: skip


@rig.command("add")
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
@click.argument("rig_file", type=click.Path(dir_okay=False, path_type=Path))
def rig_add(workspace: Path, rig_file: Path):
    """Check RIG_FILE and store it in WORKSPACE's catalog (a newer version replaces the old)."""
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        name = ws.add_rig(rig_file)
    console.print(f"rig {name!r} stored in {workspace}")


@rig.command("list")
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
def rig_list(workspace: Path):
    """List the rigs stored in WORKSPACE."""
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace, readonly=True) as ws:
        for name, sha in ws.rigs():
            console.print(f"{name}  sha256 {sha[:16]}", highlight=False)


if __name__ == "__main__":
    main()

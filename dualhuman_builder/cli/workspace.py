"""`dualhuman init`, `status`, `actor`, `rig`: workspaces, their actors and rigs."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main


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
@click.option("--long", "long_", is_flag=True,
              help="One line per stage run: state, parameters hash, end time, artifacts; errors in full.")
@click.option("--verify", is_flag=True, help="Also re-hash every artifact and take file against the catalog.")
@click.option("--json", "as_json", is_flag=True, help="Print every run's state, hash, end time, error and artifact count as JSON.")
def status(workspace: Path, long_: bool, verify: bool, as_json: bool):
    """Show which pipeline stages have run for each take and sequence of WORKSPACE.

    One line per take, and an indented line per sequence of it; one column per stage, in
    pipeline order, with a mark for its state: done, stale (a stage it reads has a new result
    since: run it again), failed, running, interrupted (its process is gone), or not run yet.
    scene, devices and capture run per sequence, the other stages per take. Runs that are not
    done are listed below with the reason. A re-run that failed keeps the previous result and its
    state (--long shows the failure). Then each take the quality gates flagged (`dualhuman gates`),
    with its flags. Control characters in names are shown escaped (\\x1b).

    Read-only: works on a workspace you cannot write to. Exit status 1 when --verify finds a problem.

    \b
    Examples:
      dualhuman status WS
      dualhuman status WS --long
      dualhuman status WS --verify
    """
    from rich.markup import escape

    from dualhuman_builder.cli.console import is_utf8, status_grid, status_long
    from dualhuman_builder.pipeline import STAGES
    from dualhuman_builder.workspace import Workspace
    from dualhuman_builder.workspace.catalog import take_flags
    from dualhuman_builder.workspace.workspace import printable

    with Workspace.open(workspace, readonly=True) as ws:
        rows = ws.status_rows()
        problems = ws.verify() if verify else []
        quality = take_flags(ws.conn)  # the quality gates' verdicts (`dualhuman gates`)
        if as_json:  # JSON escapes control characters
            click.echo(json.dumps({"rows": rows, "problems": problems, "quality": quality}, indent=2))
        else:
            title = f"workspace {ws.root}"
            if long_:
                lines = status_long(rows, STAGES, title)
            else:
                lines = status_grid(rows, STAGES, title, width=console.width, unicode=is_utf8(console))
            for line in lines:
                console.print(line, soft_wrap=True, highlight=False)
            for take, q in quality.items():  # the quality gates' flags (`dualhuman gates`)
                if not q["flags"]:
                    continue
                late = f" (from before {', '.join(q['outdated'])} ran again: `dualhuman gates {ws.root} --take {take}`)" \
                    if q["outdated"] else ""  # fmt: skip
                console.print(f"[red]flagged[/] {escape(printable(take))}: {len(q['flags'])} flag(s){escape(printable(late))}",
                              highlight=False, soft_wrap=True)  # fmt: skip
                for f in q["flags"]:
                    console.print(f"  {f['gate']} ({f['stage']}): {escape(printable(f['message']))}", highlight=False,
                                  soft_wrap=True)  # fmt: skip
            if verify:
                for p in problems:
                    console.print(f"[red]problem:[/] {escape(printable(p))}", highlight=False, soft_wrap=True)
                console.print("[green]all artifacts match the catalog[/]" if not problems else f"{len(problems)} problem(s)")
    if problems:
        sys.exit(1)


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


@main.group()
def rig():
    """Rig files: sources by URL, actors, character IDs and tracker placement (rigs/*.toml)."""


@rig.command("check")
@click.argument("rig_file", type=click.Path(dir_okay=False, path_type=Path))
def rig_check(rig_file: Path):
    """Check RIG_FILE: sources, actors, MVN character IDs, tracker segments, and its segment
    mapping's bones. Prints a summary, or the first problem with its fix (exit status 2).

    Then a warning for what would let strangers in (the rig stays valid, exit status 0): a UDP
    source listening on every interface without allow=, a vive+udp source without serials=, a
    worn tracker that no serials= lists."""
    from dualhuman_builder.rig import load_rig

    r = load_rig(rig_file)
    console.print(f"rig {r.name!r} is valid: {len(r.sources)} sources, {len(r.actors)} actors, "
                  f"mapping {r.mapping.path.name}")  # fmt: skip
    for s in r.sources:
        console.print(f"  source {s.name}: {s.url}", highlight=False, markup=False, soft_wrap=True)
    for a in r.actors:
        console.print(f"  actor {a.name}: source {a.source}, character {a.character}, {len(a.trackers)} trackers",
                      highlight=False)  # fmt: skip
    for w in r.warnings():
        console.print(f"warning: {w}", highlight=False, markup=False, soft_wrap=True)


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

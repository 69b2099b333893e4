"""`dualhuman gates` and `dualhuman review`: the quality gates of a workspace's takes and its review page."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main


@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--take", "takes", multiple=True, help="Check only this take (repeatable; default: every take).")
@click.option("--config", "config", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="A TOML file of thresholds overriding the bundled gates.toml key by key.")
@click.option("--json", "as_json", is_flag=True, help="Print each take's flags and skipped gates as JSON.")
@click.option("--fail-on-flags", is_flag=True, help="Exit with status 1 when a take is flagged.")
def gates(workspace: Path, takes: tuple[str, ...], config: Path | None, as_json: bool, fail_on_flags: bool):
    """Check takes against the quality gates and store their flags in the catalog.

    Gates: tracker loss per tracker (fuse), the sync report's warnings and the suit's root drift
    against the trackers (sync), residuals to the trackers, penetration and foot slide (fit),
    contact flicker (contacts), render completeness (render). A gate whose stage has not run, or
    is stale, is skipped, not failed. Checking a take replaces its stored flags; `dualhuman
    status` shows them and `dualhuman export` leaves flagged takes out unless --include-flagged.
    The thresholds, each with its reason: dualhuman_builder/quality/gates.toml.

    \b
    Examples:
      dualhuman gates WS
      dualhuman gates WS --take T001 --config strict-gates.toml
    """
    from rich.markup import escape

    from dualhuman_builder.quality.gates import check_take, load_config, stored_flags
    from dualhuman_builder.workspace import Workspace
    from dualhuman_builder.workspace.workspace import printable

    cfg = load_config(config)  # a bad config fails before anything is stored
    report = {}
    with Workspace.open(workspace) as ws:
        names = list(takes) or ws.takes()
        for t in names:
            ws.take(t)  # every take named exists before any is checked
        for t in names:
            flags = check_take(ws, t, cfg)
            report[t] = stored_flags(ws, t).get(t, {})
            if as_json:
                continue
            head = f"[red]{len(flags)} flag(s)[/]" if flags else "[green]clean[/]"
            console.print(f"{escape(printable(t))}: {head} ({len(report[t].get('evaluated', []))} gate(s) evaluated, "
                          f"{len(report[t].get('skipped', {}))} skipped)", highlight=False, soft_wrap=True)  # fmt: skip
            for f in flags:
                console.print(f"  {f.gate} ({f.stage}): {escape(printable(f.message))}", highlight=False, soft_wrap=True)
    if as_json:
        click.echo(json.dumps(report, indent=2))
    else:
        flagged = [t for t, r in report.items() if r.get("flags")]
        console.print(f"{len(report)} take(s) checked, {len(flagged)} flagged", highlight=False)
    if fail_on_flags and any(r.get("flags") for r in report.values()):
        sys.exit(1)


@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--out", type=click.Path(path_type=Path), default=None,
              help="Where to write the page (default: WORKSPACE/review.html); its links are relative to it.")
def review(workspace: Path, out: Path | None):
    """Write a static HTML review page of WORKSPACE: every take with its stages, flags and figures.

    One file, no server: open it in a browser. Each take links to its fit report, contact sheet,
    renders and sync report where they exist; the table sorts by any column and filters by verdict
    (flagged, clean, not checked), gate and text. Flags come from `dualhuman gates`; a take never
    checked shows as "not checked". Reads the workspace only.

    \b
    Examples:
      dualhuman review WS
      dualhuman review WS --out /tmp/review.html
    """
    from dualhuman_builder.quality.review import write_review
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace, readonly=True) as ws:
        path = write_review(ws, out)
    console.print(f"review page: {path}", highlight=False, soft_wrap=True)

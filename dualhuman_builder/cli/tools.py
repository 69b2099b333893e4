"""`dualhuman doctor` and `dualhuman demo`."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main


@main.command()
@click.option("--json", "as_json", is_flag=True, help="Print the checks as JSON.")
@click.option("--no-render", is_flag=True, help="Skip the Mitsuba test renders, the slowest checks (reported as not probed).")
def doctor(as_json: bool, no_render: bool):
    """Check what works on this machine, and say how to fix what does not.

    Checks Python and package versions, torch and CUDA, the anny body-model cache, each
    Mitsuba variant actually rendering a tiny scene (scalar, LLVM with the libLLVM it used, CUDA),
    libigl, warp, SQLite, and which capture backends can open (UDP, serial ports, CAN, USB).
    Where there is no NVIDIA GPU, the CUDA checks are skipped with the reason. Exit status 1
    when a required piece is missing.

    \b
    Examples:
      dualhuman doctor
      dualhuman doctor --no-render --json
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
    """Run the whole pipeline on simulated actors, into WORKSPACE (default ./demo-workspace;
    created if missing, reused if present: a second run only checks that everything is up to
    date). Ends with the workspace's status and where the outputs are.

    Example:  dualhuman demo /tmp/demo-ws
    """
    from dualhuman_builder.cli.console import is_utf8, status_grid
    from dualhuman_builder.demo import run_demo
    from dualhuman_builder.pipeline import STAGES
    from dualhuman_builder.workspace import Workspace

    result = run_demo(workspace, log=lambda msg: console.print(f"[dim]demo:[/] {msg}", highlight=False))
    with Workspace.open(workspace, readonly=True) as ws:
        lines = status_grid(ws.status_rows(), STAGES, f"workspace {ws.root}", width=console.width, unicode=is_utf8(console))
    for line in lines:
        console.print(line, soft_wrap=True, highlight=False)
    console.print(f"demo finished in {result.seconds:.1f} s; its outputs:")
    images = [p for k, p in result.outputs.items() if k.startswith("views/")]
    for _, path in sorted((k, p) for k, p in result.outputs.items() if not k.startswith("views/")):
        console.print(f"  {path}", highlight=False, soft_wrap=True)
    if images:
        views = images[0].parents[2]
        console.print(f"  {views}/<view>/{{rgb,depth,mask}}/<frame>: {len(images)} images", highlight=False, soft_wrap=True)
    console.print("look at preview.png, strip.png and contact_sheet.png first; preview.glb opens in any glTF viewer "
                  "(Blender, MeshLab, a browser); the dataset is in export/ (README.md is its card)",
                  highlight=False, soft_wrap=True)  # fmt: skip

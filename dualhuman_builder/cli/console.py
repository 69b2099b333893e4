"""Terminal presentation for the CLI (rich tables); library code never prints."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table

STATE_STYLE = {
    "done": "[green]done[/]",
    "failed": "[red]failed[/]",
    "running": "[yellow]running[/]",
    "interrupted": "[magenta]interrupted[/]",
}


def print_error(console: Console, err) -> None:
    kw = {"highlight": False, "soft_wrap": True}
    console.print(f"[bold red]error:[/] {escape(str(getattr(err, 'message', err)))}", **kw)
    if getattr(err, "path", None) is not None:
        console.print(f"  [dim]where:[/] {escape(str(err.path))}", **kw)
    if getattr(err, "fix", None):
        console.print(f"  [bold]fix:[/] {escape(err.fix)}", **kw)


def status_table(rows: list[dict[str, Any]], stages: tuple[str, ...], title: str) -> Table:
    """Takes and sequences (rows) x stages (columns); a cell shows the run's state and hash."""
    seen = [s for s in stages if any(s in r["stages"] for r in rows)]
    extra = sorted({s for r in rows for s in r["stages"]} - set(stages))
    columns = seen + extra or list(stages[:1])
    table = Table(title=title, title_justify="left")
    table.add_column("take", style="bold")
    table.add_column("sequence")
    table.add_column("frames", justify="right")
    for s in columns:
        table.add_column(s)
    for r in rows:
        frames = "" if "frames" not in r else f"{r['frames'][0]}-{r['frames'][1]}"
        cells = []
        for s in columns:
            info = r["stages"].get(s)
            if info is None:
                cells.append("[dim]-[/]")
            else:
                cells.append(f"{STATE_STYLE.get(info['state'], info['state'])} [dim]{info['hash']}[/]")
        table.add_row(escape(r["take"]), escape(r["sequence"]) if r["sequence"] else "[dim](take)[/]", frames, *cells)
    return table


def body_info_tables(info: dict[str, Any], bones: bool, mapping: bool, regions: bool) -> list:
    mesh = info["mesh"]
    head = Table(title=f"body model {info['model']} {info['version']}", title_justify="left", show_header=False)
    head.add_column(style="bold")
    head.add_column()
    head.add_row("vertices / faces", f"{info['vertices']:,} / {info['faces']:,}")
    head.add_row("bones", str(len(info["bones"])))
    head.add_row("shape parameters", ", ".join(info["shape_names"]) + "  (each in [0, 1])")
    head.add_row("stature, default shape", f"{info['stature_m_default_shape']:.3f} m")
    head.add_row("watertight", f"{mesh.watertight} ({mesh.boundary_edges} boundary, {mesh.nonmanifold_edges} non-manifold edges)")
    head.add_row("winding", f"consistent={mesh.winding_consistent}, volume {mesh.volume_m3 * 1000:.1f} L (outward)")
    head.add_row("closed components", ", ".join(str(c) for c in mesh.component_vertex_counts) + " vertices")
    head.add_row("segment mapping", info["mapping_path"])
    out: list = [head]
    if bones:
        t = Table(title="anny bones", title_justify="left")
        t.add_column("#", justify="right")
        t.add_column("bone")
        for i, b in enumerate(info["bones"]):
            t.add_row(str(i), b)
        out.append(t)
    if mapping:
        t = Table(title="MVN segment -> anny bone (T-pose direction deviation)", title_justify="left")
        for c in ("segment", "bone", "deviation", "tolerance"):
            t.add_column(c)
        for seg, bone, tol, dev in info["mapping"]:
            ok = "green" if dev <= tol else "red"
            t.add_row(seg, bone, f"[{ok}]{dev:5.1f} deg[/]", f"{tol:.0f} deg")
        out.append(t)
    if regions:
        t = Table(title="body-part regions", title_justify="left")
        t.add_column("region")
        t.add_column("vertices", justify="right")
        for name, n in info["regions"]:
            t.add_row(name, str(n))
        out.append(t)
    return out


def live_status_table(status) -> Table:
    """The recorder's live view (:class:`~dualhuman_builder.capture.recorder.LiveStatus`): per
    source rate, loss, errors and last-sample age; per actor which suit and trackers are live."""
    table = Table(title=f"take {escape(status.take)} — {status.elapsed_s:6.1f} s, {status.messages} messages",
                  title_justify="left")  # fmt: skip
    for col, just in (("source", "left"), ("kind", "left"), ("packets/s", "right"), ("samples/s", "right"),
                      ("loss", "right"), ("errors", "right"), ("last sample", "right")):  # fmt: skip
        table.add_column(col, justify=just)
    for s in status.sources:
        age = "-" if s.last_sample_age_s is None else f"{s.last_sample_age_s * 1000:.0f} ms"
        if s.last_sample_age_s is not None and s.last_sample_age_s > 0.5:
            age = f"[red]{age}[/]"
        loss = f"[red]{s.loss}[/]" if s.loss else "0"
        errors = f"[yellow]{s.errors}[/]" if s.errors else "0"
        table.add_row(escape(s.name), s.kind, f"{s.packet_rate:.0f}", f"{s.sample_rate:.0f}", loss, errors, age)
    if status.actors:
        table.add_section()
        for a in status.actors:
            suit = {"live": "[green]suit live[/]", "stale": "[red]suit stale[/]", "absent": "[red]no suit[/]"}.get(a.suit, "")
            tr = f"trackers {a.trackers_live}/{a.trackers_total}" if a.trackers_total else ""
            if a.trackers_total and a.trackers_live < a.trackers_total:
                tr = f"[yellow]{tr}[/]"
            table.add_row(f"[bold]{escape(a.name)}[/]", "actor", suit, tr, "", "", "")
    return table

"""Terminal presentation for the CLI (the status grid, rich tables, errors); library code never prints."""

from __future__ import annotations

from datetime import datetime
from typing import Any

from rich.console import Console
from rich.markup import escape
from rich.table import Table
from rich.text import Text

#: Per run state: the glyph in the status grid (Unicode, and ASCII for other terminals) and its colour.
STATE_GLYPHS = {
    "done": ("✓", "+", "green"),
    "stale": ("~", "~", "yellow"),  # done once, but an input has changed since
    "failed": ("✗", "x", "red"),
    "running": ("▶", ">", "yellow"),
    "interrupted": ("!", "!", "magenta"),
    "publishing": ("!", "!", "magenta"),  # killed while its new results replaced the old ones
    None: ("·", ".", "dim"),  # not run yet
}
STATE_WORDS = {"done": "done", "stale": "stale", "failed": "failed", "running": "running", "interrupted": "interrupted",
               "publishing": "publishing", None: "not run"}


def is_utf8(console: Console) -> bool:
    """Whether ``console`` writes UTF-8 (then the status marks are Unicode, else ASCII)."""
    return (console.encoding or "").lower().replace("-", "").startswith("utf")


def print_error(console: Console, err) -> None:
    kw = {"highlight": False, "soft_wrap": True}
    console.print(f"[bold red]error:[/] {escape(str(getattr(err, 'message', err)))}", **kw)
    if getattr(err, "path", None) is not None:
        console.print(f"  [dim]where:[/] {escape(str(err.path))}", **kw)
    if getattr(err, "fix", None):
        console.print(f"  [bold]fix:[/] {escape(err.fix)}", **kw)


def _row_name(r: dict[str, Any]) -> str:
    return r["take"] if r["sequence"] is None else f"{r['take']}/{r['sequence']}"


def _frames(r: dict[str, Any]) -> str:
    return "" if "frames" not in r else f"{r['frames'][0]}-{r['frames'][1]}"


def printable_row(row: dict[str, Any]) -> dict[str, Any]:
    """A status row with its names and messages safe to print: control and format characters
    escaped (a take name cannot move the cursor or reorder the line)."""
    from dualhuman_builder.workspace.workspace import printable

    def lines(value):  # an error's lines stay lines; names are escaped whole
        return None if value is None else "\n".join(printable(line) for line in str(value).split("\n"))

    out = {**row, "take": printable(row["take"]), "sequence": None if row["sequence"] is None else printable(row["sequence"])}
    out["stages"] = {printable(n): {**info, "error": lines(info.get("error"))} for n, info in row["stages"].items()}
    return out


def status_grid(rows: list[dict[str, Any]], stages, title: str, width: int = 80, unicode: bool = True) -> list[Text]:
    """The lines of ``dualhuman status``: one line per take and per sequence of it (indented),
    one column per stage (``stages``: objects with ``name`` and ``per``, in pipeline order) with a
    glyph for its state where the stage runs at that level, a legend, and the runs that need a look
    (failed, interrupted, running) with their errors. Plain text without styles where the console
    has no colours; no line is cut: where the grid would pass ``width``, names go on their own line.
    Names, errors and the title are printed escaped (:func:`printable_row`)."""
    from dualhuman_builder.workspace.workspace import printable

    rows, title = [printable_row(r) for r in rows], printable(title)
    names = [s.name for s in stages]
    per = {s.name: s.per for s in stages}
    names += sorted({n for r in rows for n in r["stages"]} - set(names))  # stages the registry no longer has
    pick = 0 if unicode else 1
    out = [Text(title, style="bold")]
    if not rows:
        out.append(Text("no takes yet", style="dim"))
        return out
    labels = [r["take"] if r["sequence"] is None else "  " + r["sequence"] for r in rows]
    frames = [_frames(r) for r in rows]
    name_w = max(len(x) for x in labels)
    frames_w = max(len(x) for x in frames)
    grid_w = sum(len(n) for n in names) + len(names) - 1
    left = name_w + 2 + (frames_w + 2 if frames_w else 0)
    stacked = left + grid_w > width
    indent = 4 if stacked else left
    out.append(Text(" " * indent + " ".join(names), style="bold"))
    for r, label, fr in zip(rows, labels, frames):
        level = "take" if r["sequence"] is None else "sequence"
        line = Text()
        head = label.ljust(name_w) + ("  " + fr.rjust(frames_w) if frames_w else "")
        line.append(head.rstrip() if stacked else head.ljust(indent), style="bold" if level == "take" else "")
        if stacked:
            out.append(line)
            line = Text(" " * indent)
        cells = Text()
        for i, n in enumerate(names):
            info = r["stages"].get(n)
            if info is None and per.get(n, level) != level:
                cell, style = " ", ""
            else:
                state = None if info is None else info["state"]
                glyphs = STATE_GLYPHS.get(state, ("?", "?", "bold"))
                cell, style = glyphs[pick], glyphs[2]
            pad = len(n) - 1
            cells.append(" " * (pad // 2))
            cells.append(cell, style=style)
            cells.append(" " * (pad - pad // 2) + (" " if i < len(names) - 1 else ""))
        cells.rstrip()
        line.append_text(cells)
        line.rstrip()
        out.append(line)
    # "publishing" shares the interrupted mark and is left out of the legend (a run killed mid-publication)
    legend = "  ".join(f"{g[pick]} {STATE_WORDS[k]}" for k, g in STATE_GLYPHS.items() if k != "publishing")
    out.append(Text(""))
    hint = "(--long: hashes, times)"
    if len(legend) + 3 + len(hint) <= width:
        out.append(Text(legend + "   " + hint, style="dim"))
    else:
        out += [Text(legend, style="dim"), Text(hint, style="dim")]
    for r in rows:
        for n in names:
            info = r["stages"].get(n)
            if info is not None and info["state"] != "done":
                glyphs = STATE_GLYPHS.get(info["state"], ("?", "?", "bold"))
                line = Text(f"{_row_name(r)} {n}: ")
                line.append(info["state"], style=glyphs[2])
                if info.get("error"):
                    line.append(f": {info['error'].strip().splitlines()[0]}")
                out.append(line)
    return out


def status_long(rows: list[dict[str, Any]], stages, title: str) -> list[Text]:
    """``dualhuman status --long``: per take and per sequence, one line per stage run (state,
    parameters hash, when it ended, how many artifacts), errors in full below a failed run; names,
    errors and the title escaped as in :func:`status_grid`."""
    from dualhuman_builder.workspace.workspace import printable

    rows, title = [printable_row(r) for r in rows], printable(title)
    names = [s.name for s in stages]
    names += sorted({n for r in rows for n in r["stages"]} - set(names))
    out = [Text(title, style="bold")]
    if not rows:
        out.append(Text("no takes yet", style="dim"))
        return out
    stage_w = max(len(n) for n in names)
    for r in rows:
        head = Text(_row_name(r), style="bold")
        if "frames" in r:
            head.append(f"  frames {_frames(r)}")
        out.append(head)
        ran = [n for n in names if n in r["stages"]]
        if not ran:
            out.append(Text("  no stage run yet", style="dim"))
        for n in ran:
            info = r["stages"][n]
            style = STATE_GLYPHS.get(info["state"], ("?", "?", "bold"))[2]
            line = Text(f"  {n.ljust(stage_w)}  ")
            line.append(info["state"].ljust(11), style=style)
            line.append(f"  {info['hash']}  {_when(info.get('ended_at'))}")
            n_art = info.get("artifacts")
            if n_art is not None:
                line.append(f"  {n_art} artifact{'' if n_art == 1 else 's'}")
            out.append(line)
            for err_line in (info.get("error") or "").strip().splitlines():
                out.append(Text(f"      {err_line}", style="red"))
    return out


def _when(stamp: str | None) -> str:
    """A catalog time stamp (ISO 8601) in local time to the second; ``-`` when there is none."""
    if not stamp:
        return "-"
    try:
        return datetime.fromisoformat(stamp).astimezone().strftime("%Y-%m-%d %H:%M:%S")
    except ValueError:
        return stamp


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
    source rate, loss, errors, last-sample age and its state where it is not recording (``lost``,
    ``raw only``); per actor which suit and trackers are live."""
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
        kind = s.kind if s.state == "recording" else f"{s.kind} [red]{s.state}[/]"  # lost, or raw only
        table.add_row(escape(s.name), kind, f"{s.packet_rate:.0f}", f"{s.sample_rate:.0f}", loss, errors, age)
    if status.actors:
        table.add_section()
        for a in status.actors:
            suit = {"live": "[green]suit live[/]", "stale": "[red]suit stale[/]", "absent": "[red]no suit[/]"}.get(a.suit, "")
            tr = f"trackers {a.trackers_live}/{a.trackers_total}" if a.trackers_total else ""
            if a.trackers_total and a.trackers_live < a.trackers_total:
                tr = f"[yellow]{tr}[/]"
            table.add_row(f"[bold]{escape(a.name)}[/]", "actor", suit, tr, "", "", "")
    return table

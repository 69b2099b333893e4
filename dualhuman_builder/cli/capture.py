"""`dualhuman capture`, `log`, `replay`, `import`: recording takes and reading them back."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, err_console, main


@main.command("import")
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
@click.argument("files", nargs=-1, required=True, metavar="FILE...",
                type=click.Path(dir_okay=False, exists=True, path_type=Path))  # fmt: skip
@click.option("--take", default=None,
              help="Take name (default: a .mcap file's recorded take name; else the file name without its suffix, made safe).")
@click.option("--actor", "actors", multiple=True,
              help="MVNX/BVH: a registered actor who wears the suit (`dualhuman actor add`); with several MVNX files, "
                   "one --actor per file, in order.")  # fmt: skip
@click.option("--scale", type=float, default=None, help="BVH only: file units to metres (default: detected, m/cm/mm).")
@click.option("--z-up", is_flag=True, help="BVH only: the file is Z-up (BVH is usually Y-up).")
def import_(workspace: Path, files: tuple[Path, ...], take: str | None, actors: tuple[str, ...], scale: float | None,
            z_up: bool):  # fmt: skip
    """Import a recorded FILE into WORKSPACE as a take: an Xsens MVN XML export (.mvnx, read
    streaming; calibration poses and every per-frame array kept), a Biovision .bvh, or a take file
    recorded by `dualhuman capture` (.mcap). Several .mvnx files (MVN exports one subject per file)
    of one recording make one take of several suits, in order.

    MVNX and BVH: the file is copied into WORKSPACE/takes/<take>/ next to the skeleton track read
    from it (skeleton.npz, Y-up metres), and the take is registered with checksums.

    MCAP: the whole file is checked first (one cut off by a crash or a full disk is refused: run
    `dualhuman log repair` on it first); a file already in WORKSPACE/takes/<take>/ (where
    `capture -w` records) is registered where it is, another is copied there. This registers a
    capture whose registration failed (say, the disk filled up as it ended): never record it again.

    \b
    Examples:
      dualhuman import WS take3.mvnx --actor alice
      dualhuman import WS alice.mvnx bob.mvnx --take T1 --actor alice --actor bob
      dualhuman import WS WS/takes/T001/T001.mcap
    """
    from rich.markup import escape

    from dualhuman_builder.capture.importers import import_files
    from dualhuman_builder.workspace import Workspace
    from dualhuman_builder.workspace.workspace import printable

    if len(files) > 1 and any(f.suffix.lower() != ".mvnx" for f in files):
        raise click.UsageError("several files make one take only when every one is an .mvnx export")
    if len(actors) > len(files):
        raise click.UsageError(f"{len(actors)} --actor for {len(files)} file(s): give one per file, in order")
    file = files[0]
    if file.suffix.lower() == ".mcap":
        from dualhuman_builder.capture.stage import register_take_file

        if actors or scale is not None or z_up:
            raise click.UsageError("--actor, --scale and --z-up apply to .mvnx and .bvh files; a take file names its actors")
        with Workspace.open(workspace) as ws:
            with console.status(f"checking {file.name}..."):
                t = register_take_file(ws, file, take=take, log=lambda m: console.print(escape(m), highlight=False))
        counts = sum(t.sample_counts.values())
        console.print(escape(f"registered {file.name} as take {printable(t.name)!r}: {counts:,} samples on "
                             f"{len(t.sample_counts)} topics ({t.duration_s or 0:.1f} s), actors "
                             f"{', '.join(map(printable, t.actors)) or 'none registered'}"), highlight=False, soft_wrap=True)  # fmt: skip
        if t.meta.get("unregistered_actors"):
            console.print(escape(f"  actors not in the workspace: {', '.join(map(printable, t.meta['unregistered_actors']))} "
                                 f"(add them with `dualhuman actor add`)"), highlight=False, soft_wrap=True)  # fmt: skip
        if t.meta.get("rig_name") and t.rig is None:
            console.print(escape(f"  rig {printable(t.meta['rig_name'])!r} is not in the workspace (`dualhuman rig add`)"),
                          highlight=False, soft_wrap=True)  # fmt: skip
        console.print(escape(f"  file: {ws.root / t.files[0]['path']}"), highlight=False, soft_wrap=True)
        return
    with Workspace.open(workspace) as ws:
        with console.status(f"reading {', '.join(f.name for f in files)}...") as spinner:
            results = import_files(ws, files, take=take, actors=list(actors) + [None] * (len(files) - len(actors)),
                                   scale=scale, up="z" if z_up else "y", progress=lambda m: spinner.update(m))  # fmt: skip
    for file, r in zip(files, results):
        _print_import(file, r)


def _print_import(file: Path, r) -> None:
    """What one imported file gave (an :class:`~dualhuman_builder.capture.importers.ImportResult`)."""
    from rich.markup import escape

    console.print(f"imported {file.name} as take {r.take!r}: {r.frames:,} frames at {r.fps:g} fps "
                  f"({r.duration_s:.2f} s), {r.segments} segments", highlight=False, soft_wrap=True)  # fmt: skip
    if r.format == "mvnx":
        console.print(f"  subject {r.subject or '(no label)'}; calibration poses: "
                      f"{', '.join(r.calibration_poses) or 'none'}", highlight=False, soft_wrap=True)  # fmt: skip
        if r.arrays:
            console.print(f"  per-frame arrays: {', '.join(r.arrays)}", highlight=False, soft_wrap=True)
    for note in r.notes:
        console.print(f"  [dim]{escape(note)}[/]", highlight=False, soft_wrap=True)
    console.print(f"  files in {r.source.parent}", highlight=False, soft_wrap=True)


@main.command()
@click.option("--rig", "rig_file", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Rig file naming the sources and who wears what (e.g. rigs/studio.toml).")
@click.option("--source", "sources", multiple=True, metavar="[NAME=]URL",
              help="A source without a rig file; repeatable (mvn+udp://:9763, vive+udp://:8051, "
                   "xbus:///dev/ttyUSB0, mti+can://socketcan/can0, vive+usb://, sim://handshake?seed=3).")
@click.option("--actor", "actors", multiple=True, metavar="NAME=SOURCE#CHARACTER",
              help="Bind an actor to an MVN character of a --source, e.g. alice=mvn1#0; repeatable.")
@click.option("--take", required=True, help="Take name (letters, digits, - and _), e.g. T001.")
@click.option("--duration", type=click.FloatRange(min=0, min_open=True), default=None,
              help="Seconds to record (default: until Ctrl-C; a sim:// take ends when it has played).")
@click.option("-w", "--workspace", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Workspace: the take goes to WS/takes/TAKE/TAKE.mcap and into its catalog.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Take file to write (default with --workspace: inside it).")
@click.option("--sim-speed", type=float, default=1.0, show_default=True,
              help="For sim:// takes: play the simulated devices this many times faster than real time.")
@click.option("--foxglove-hz", type=float, default=60.0, show_default=True,
              help="Body-pose transforms per second and actor for Foxglove (0: none).")
@click.option("--quiet", is_flag=True, help="No live status; only the summary at the end.")
def capture(rig_file, sources, actors, take, duration, workspace, out, sim_speed, foxglove_hz, quiet):
    """Record a take: every source of a rig (or the --source ones) into one MCAP file with the raw
    bytes of every datagram and frame, the decoded samples, and body poses Foxglove can show.

    A live table shows each source's rate, loss, errors and the age of its last sample, and
    which actors' suits and trackers are live. Stop with Ctrl-C or --duration. A device lost or a
    full disk mid-take stops it cleanly: everything before is kept (exit status 1). With -w, a take
    that was recorded but could not be registered (a full disk) is kept too (exit status 1):
    register it with `dualhuman import WS WS/takes/TAKE/TAKE.mcap` once the cause is fixed.

    \b
    Examples:
      dualhuman capture --rig rigs/studio.toml --take T001 --duration 60 -w WS
      dualhuman capture --source 'sim://handshake?seed=3' --take S1 --out S1.mcap
      dualhuman capture --source suits=mvn+udp://:9763 --actor alice=suits#0 \\
          --take T2 --out T2.mcap
    """
    import math

    from rich.live import Live

    from dualhuman_builder.capture.recording import capture_take, default_take_path, plan_capture
    from dualhuman_builder.cli.console import live_status_table, print_error
    from dualhuman_builder.errors import DualhumanError

    plan = plan_capture(rig_file, sources, actors)
    if rig_file is not None and not quiet:
        from rich.markup import escape

        from dualhuman_builder.rig import load_rig

        for w in load_rig(rig_file).warnings():  # what `rig check` warns about: strangers' packets let in
            err_console.print(f"[yellow]warning:[/] {escape(w)}", highlight=False, soft_wrap=True)
    if out is None:
        if workspace is None:
            raise click.UsageError("say where the take goes: --workspace WS or --out TAKE.mcap")
        out = default_take_path(workspace, take)
    if workspace is not None:
        from dualhuman_builder.workspace import Workspace

        with Workspace.open(workspace, readonly=True) as ws:
            if take in ws.takes():
                raise DualhumanError(f"take {take!r} is already in the workspace", path=workspace,
                                     fix="record under another --take name")  # fmt: skip
        if Path(out).exists():
            raise DualhumanError(f"take {take!r} was recorded to {out} already, but is not in the workspace's catalog",
                                 fix=f"register that recording with `dualhuman import {workspace} {out}`, or record "
                                     "under another --take name")  # fmt: skip
    speed = math.inf if sim_speed == 0 else sim_speed
    log = None if quiet else (lambda m: err_console.print(f"[dim]{m}[/]", highlight=False))
    try:
        if quiet or not console.is_terminal:
            result = capture_take(plan, out, take=take, duration=duration, workspace=workspace, progress=log,
                                  sim_speed=speed, foxglove_hz=foxglove_hz)  # fmt: skip
        else:
            with Live(console=console, refresh_per_second=4, transient=False) as live:
                result = capture_take(plan, out, take=take, duration=duration, workspace=workspace, progress=log,
                                      sim_speed=speed, foxglove_hz=foxglove_hz,
                                      on_status=lambda st: live.update(live_status_table(st)))  # fmt: skip
    except DualhumanError as e:
        if workspace is None or not isinstance(e.__cause__, DualhumanError) or not Path(out).is_file():
            raise
        # recorded, but not registered (the catalog could not be written): keep it and say how to register it
        print_error(err_console, DualhumanError(e.message, fix=f"{e.fix + '; then ' if e.fix else ''}register the "
                                                f"recording with `dualhuman import {workspace} {out}` (it is kept; do not "
                                                "record it again)"))  # fmt: skip
        sys.exit(1)
    counts = result.samples_per_topic
    console.print(f"take {result.take}: {result.duration_s:.1f} s, {sum(counts.values())} samples on {len(counts)} "
                  f"topics, {result.messages} messages -> {result.path}", highlight=False)  # fmt: skip
    for name, st in result.source_stats.items():
        shown = ", ".join(f"{k} {v}" for k, v in sorted(st.items()) if v and k not in ("bytes",))
        console.print(f"  {_safe(name)}: {_safe(shown)}", highlight=False)
    from rich.markup import escape

    from dualhuman_builder.workspace.workspace import printable

    # every event that says data was lost or a source ended; of the rest, the first 20
    vital = ("source-lost", "decoding-failed", "kernel-drops", "decoder-error")
    shown_events = [ev for i, ev in enumerate(result.events) if i < 20 or ev["kind"] in vital]
    for ev in shown_events:
        head = printable(f"{ev['source']} {ev['entity']}: {ev['kind']}")
        console.print(f"  [yellow]{escape(head)}[/] {escape(printable(ev['message']))}", highlight=False)
    if len(shown_events) < len(result.events):
        console.print(f"  ... {len(result.events) - len(shown_events)} more events in the take "
                      f"(`dualhuman log dump {result.path} --topic events`)", highlight=False)  # fmt: skip
    if result.error:
        print_error(err_console, DualhumanError(result.error, fix=result.fix or "the take is kept up to the failure; "
                                                f"check it with `dualhuman log check {result.path}`"))  # fmt: skip
        sys.exit(1)


def _safe(text) -> str:
    """Text read from a take file, safe to print: control characters and rich markup escaped."""
    from rich.markup import escape

    from dualhuman_builder.workspace.workspace import printable

    return escape(printable(str(text)))


@main.group()
def log():
    """Inspect, repair and dump take files (MCAP)."""


@log.command("check")
@click.argument("take_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print the report as JSON.")
def log_check(take_file: Path, as_json: bool):
    """Read a whole take (CRCs checked) and report what it holds and what is lost.

    Exit status 0 when complete and intact, 1 when it needs `dualhuman log repair`
    (cut off by a crash or a full disk) or has damaged chunks."""
    from dualhuman_builder.capture.log.reader import check_take

    rep = check_take(take_file)
    if as_json:
        console.print_json(data=rep.to_dict())
    else:
        state = "[green]complete[/]" if rep.ok else ("[yellow]incomplete[/]" if not rep.complete else "[red]damaged[/]")
        dur = "" if rep.first_ns is None else f", {(rep.last_ns - rep.first_ns) / 1e9:.1f} s"
        console.print(f"{take_file}: {state}, {rep.messages} messages in {rep.chunks} chunks{dur}, "
                      f"{rep.size} bytes ({rep.lost_bytes} unreadable)", highlight=False)  # fmt: skip
        for topic, n in sorted(rep.per_topic.items()):  # names from the file: printed escaped
            console.print(f"  {_safe(topic)}: {n}", highlight=False)
        for topic, n in sorted(rep.lost_messages.items()):
            console.print(f"  [yellow]lost:[/] {_safe(topic)}: {n} messages in damaged chunks", highlight=False)
        for p in rep.problems:
            console.print(f"  [yellow]problem:[/] {_safe(p)}", highlight=False)
    sys.exit(0 if rep.ok else 1)


@log.command("repair")
@click.argument("take_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the repaired take here (default: in place; the original is kept as NAME.damaged.mcap).")
def log_repair(take_file: Path, out: Path | None):
    """Rebuild a take cut off by a crash, kill -9 or a full disk, or with damaged chunks: everything
    readable, with a full index. Channels whose records were damaged are recovered from the take's
    summary; samples the raw bytes hold that were never written (the decoding lagged, the disk
    filled) are re-decoded and written. Says what was lost: bytes, and messages per topic."""
    from dualhuman_builder.capture.log.repair import repair_take

    rep = repair_take(take_file, out)
    lost = sum(rep.lost_messages.values())
    console.print(f"repaired {rep.path}: {rep.messages} messages kept, {sum(rep.redecoded.values())} samples "
                  f"re-decoded from the raw bytes; lost: {rep.lost_bytes} bytes"
                  + (f", {lost} messages" if lost else ""), highlight=False)  # fmt: skip
    if rep.original:
        console.print(f"  original kept as {rep.original}", highlight=False)
    for topic, n in sorted(rep.lost_messages.items()):
        console.print(f"  [yellow]lost:[/] {_safe(topic)}: {n} messages", highlight=False)
    for topic, n in sorted(rep.redecoded.items()):
        console.print(f"  re-decoded: {_safe(topic)}: {n} samples", highlight=False)
    for line in rep.recovered:
        console.print(f"  recovered: {_safe(line)}", highlight=False)
    for p in rep.problems:
        console.print(f"  [yellow]problem:[/] {_safe(p)}", highlight=False)
    for note in rep.notes:
        console.print(f"  [yellow]note:[/] {_safe(note)}", highlight=False)


@log.command("dump")
@click.argument("take_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--jsonl", is_flag=True, help="One JSON object per line (the only format; the default).")
@click.option("--raw", is_flag=True, help="Also dump the raw packets (hex).")
@click.option("--topic", "topics", multiple=True, help="Only topics starting with this; repeatable.")
def log_dump(take_file: Path, jsonl: bool, raw: bool, topics: tuple[str, ...]):
    """Print every decoded sample: source, character or device, device and host timestamps (ns),
    fields in SI units (metres, m/s, m/s^2, rad/s; quaternions x, y, z, w; Y-up world).

    Example:  dualhuman log dump T001.mcap --jsonl | head
    """
    from dualhuman_builder.capture.log.reader import dump_jsonl

    try:
        dump_jsonl(take_file, sys.stdout, raw=raw, topics=topics, problems=(problems := []))
    except BrokenPipeError:
        sys.stderr.close()
        return
    for p in problems:
        err_console.print(f"[yellow]problem:[/] {_safe(p)}", highlight=False)


@main.command()
@click.argument("take_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--to", "targets", multiple=True, metavar="URL",
              help="Put the raw packets back on the wire: mvn+udp://HOST:PORT, vive+udp://HOST:PORT, "
                   "xbus://PATH, mti+can://INTERFACE/CHANNEL; repeatable.")
@click.option("--speed", type=float, default=1.0, show_default=True, help="Times real time with --to (0: as fast as possible).")
@click.option("--verify", is_flag=True, help="Also re-decode the raw packets and check they give the recorded samples bit for bit.")
def replay(take_file: Path, targets: tuple[str, ...], speed: float, verify: bool):
    """Replay a take: read back its samples exactly as recorded (a summary per channel is printed;
    from Python, `replay_samples` and `read_columns` hand them to the pipeline), or with --to send
    its raw datagrams and frames to live consumers at the recorded timing.

    \b
    Examples:
      dualhuman replay T001.mcap --verify
      dualhuman replay T001.mcap --speed 1 --to mvn+udp://127.0.0.1:9763 \\
          --to vive+udp://127.0.0.1:8051
    """
    import math
    import time

    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.capture.replay import replay_to, verify_replay

    if targets:
        rep = replay_to(take_file, list(targets), speed=math.inf if speed == 0 else speed)
        console.print(f"sent {rep.packets} packets of {rep.recorded_s:.1f} s recorded in {rep.elapsed_s:.2f} s"
                      + "".join(f"\n  {u}: {n}" for u, n in rep.sent.items()), highlight=False)  # fmt: skip
        if rep.skipped_sources:
            console.print(f"  not sent (no --to for their kind): {_safe(', '.join(rep.skipped_sources))}", highlight=False)
        return
    t = time.perf_counter()
    problems: list[str] = []
    columns = read_columns(take_file, problems)
    dt = time.perf_counter() - t
    n = sum(c.count for c in columns.values())
    firsts = [int(c.columns["host_time_ns"][0]) for c in columns.values() if c.count]
    lasts = [int(c.columns["host_time_ns"][-1]) for c in columns.values() if c.count]
    span = (max(lasts) - min(firsts)) / 1e9 if firsts else 0.0
    console.print(f"{n} samples over {span:.1f} s of host time, read in {dt:.2f} s", highlight=False)
    for topic, c in sorted(columns.items()):
        odd = ""
        if c.odd:
            present = c.columns.get("segment_names__present")
            some = [] if present is None else [g for g, a in zip(c.columns["segment_names"], present.all(axis=0))
                                               if not a]  # fmt: skip
            odd = f" ({c.odd} laid out otherwise" + (f"; segments not in every sample: {', '.join(some)})"
                                                      if some else ")")  # fmt: skip
        console.print(f"  {_safe(topic)}: {c.count} {_safe(c.sample_type)}{_safe(odd)}", highlight=False)
    if not verify:
        from dualhuman_builder.capture.log.reader import scan_take

        if not scan_take(take_file).complete:
            problems.append("the take has no index: the recording did not finish — `dualhuman log repair` "
                            "rebuilds it and writes the samples its raw bytes hold that were never written")  # fmt: skip
        for p in problems:
            console.print(f"  [yellow]problem:[/] {_safe(p)}", highlight=False)
        return
    chk = verify_replay(take_file)
    for p in chk.problems:
        console.print(f"  [yellow]problem:[/] {_safe(p)}", highlight=False)
    if chk.mismatches:
        console.print(f"[red]{chk.mismatches} of {chk.samples} samples differ[/]; first: {_safe(chk.first_mismatch)}",
                      highlight=False)  # fmt: skip
    if chk.missing:
        console.print(f"[red]{chk.missing} samples decoded from the raw bytes are not in the take[/] (its decoded "
                      f"samples lag the raw bytes): `dualhuman log repair {take_file}` writes them",
                      highlight=False)  # fmt: skip
    if chk.unreproduced:
        console.print(f"[red]{chk.unreproduced} recorded samples are not given by re-decoding the raw bytes[/]",
                      highlight=False)  # fmt: skip
    if chk.verified:
        console.print(f"[green]re-decoding the raw packets gives the recorded {chk.samples} samples bit for bit[/]")
        return
    if chk.identical:
        what = "the take is damaged" if chk.problems else "the take holds no samples and its raw packets decode to none"
        console.print(f"[red]not verified: {what}[/] ({chk.samples} samples re-decoded bit for bit)", highlight=False)
    sys.exit(1)

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
    images = [p for k, p in result.outputs.items() if k.startswith("views/")]
    for _, path in sorted((k, p) for k, p in result.outputs.items() if not k.startswith("views/")):
        console.print(f"  {path}", highlight=False, soft_wrap=True)
    if images:
        views = images[0].parents[2]
        console.print(f"  {views}/<view>/{{rgb,depth,mask}}/<frame>: {len(images)} images", highlight=False, soft_wrap=True)
    console.print("look at preview.png, strip.png and contact_sheet.png first; preview.glb opens in any glTF viewer "
                  "(Blender, MeshLab, a browser); the dataset is in export/ (README.md is its card)",
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


# --------------------------------------------------------------------------------------------- scenes
def _floats(text: str | None, what: str, n: int = 2) -> list[float] | None:
    if text is None:
        return None
    try:
        vals = [float(x) for x in text.split(",")]
    except ValueError:
        raise click.BadParameter(f"{what} must be {n} comma-separated numbers, got {text!r}") from None
    if len(vals) != n:
        raise click.BadParameter(f"{what} must be {n} comma-separated numbers, got {text!r}")
    return vals


@main.command("import")
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
@click.argument("file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--take", default=None, help="Take name (default: the file name without its suffix, made safe).")
@click.option("--actor", default=None, help="A registered actor who wears the suit (`dualhuman actor add`).")
@click.option("--scale", type=float, default=None, help="BVH only: file units to metres (default: detected, m/cm/mm).")
@click.option("--z-up", is_flag=True, help="BVH only: the file is Z-up (BVH is usually Y-up).")
def import_(workspace: Path, file: Path, take: str | None, actor: str | None, scale: float | None, z_up: bool):
    """Import a recorded FILE into WORKSPACE as a take: an Xsens MVN XML export (.mvnx, read
    streaming; calibration poses and every per-frame array kept) or a Biovision .bvh.

    The file is copied into WORKSPACE/takes/<take>/ next to the skeleton track read from it
    (skeleton.npz, Y-up metres), and the take is registered with checksums. Example:
    dualhuman import ws session3.mvnx --actor alice
    """
    from rich.markup import escape

    from dualhuman_builder.capture.importers import import_file
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        with console.status(f"reading {file.name}...") as spinner:
            r = import_file(ws, file, take=take, actor=actor, scale=scale, up="z" if z_up else "y",
                            progress=lambda m: spinner.update(m))  # fmt: skip
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


@main.group()
def scene():
    """Ground-truth two-person interaction scenes: make, inspect, preview.

    A scene is two anny bodies of different shapes performing a close interaction from
    keyframes and inverse kinematics, with ground-truth vertices and contacts (signed distance
    between the meshes). Every later stage is measured against it.
    """


@scene.command("make")
@click.option("--type", "scene_type",
              type=click.Choice(["handshake", "hug", "high_five", "push", "pat_on_back", "dance_turn", "calibration"]),
              default="handshake", show_default=True,
              help="The interaction; or 'calibration', the session's calibration motion (the actors apart, turning every "
                   "tracked segment: see `dualhuman sync --mounts-from`).")  # fmt: skip
@click.option("--seed", type=int, default=0, show_default=True, help="Draws the two actors' shapes and small variations.")
@click.option("--fps", type=float, default=30.0, show_default=True, help="Frames per second of the ground truth.")
@click.option("--tempo", type=float, default=1.0, show_default=True, help="Speed of the motion (>1 faster).")
@click.option("--duration", type=float, default=None, help="Seconds (default: the type's natural length; longer pads with standing).")
@click.option("--approach-distance", type=float, default=None, help="Pelvis-to-pelvis metres at the start (default per type).")
@click.option("--heights", default=None, metavar="A,B", help="Statures of the two actors in metres, e.g. 1.62,1.85 (default: drawn from the seed).")
@click.option("--genders", default="0.5,0.5", show_default=True, metavar="A,B", help="anny gender of each actor with --heights (0 male ... 1 female).")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Output file (default scene-TYPE-SEED.npz).")  # fmt: skip
def scene_make(scene_type, seed, fps, tempo, duration, approach_distance, heights, genders, out):
    """Generate a scene and save it (a versioned .npz: the InteractionSequence, per-vertex signed
    distances to the partner, stance masks, phases). Prints the quality measures and exits 1 if
    the scene breaks the quality contract (penetration <= 5 mm, planted feet slide <= 5 mm per
    frame, contact throughout the contact phase, joints within anatomical limits).

    Example: dualhuman scene make --type hug --seed 1 --fps 30 --out hug.npz
    """
    from dualhuman_builder.sim.scenes import SceneParams, contract_failures, make_scene

    shapes = None
    if heights is not None:
        from dualhuman_builder.body.model import get_body_model
        from dualhuman_builder.body.shape import shape_for_stature

        model = get_body_model()
        h, g = _floats(heights, "--heights"), _floats(genders, "--genders")
        shapes = tuple(shape_for_stature(model, hi, gi) for hi, gi in zip(h, g))
    try:
        params = SceneParams(type=scene_type, seed=seed, shapes=shapes, approach_distance=approach_distance,
                             tempo=tempo, duration=duration, fps=fps)  # fmt: skip
        with console.status(f"making {scene_type} seed {seed}...") as spinner:
            result = make_scene(params, log=lambda m: spinner.update(m))
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    out = out or Path(f"scene-{scene_type}-{seed}.npz")
    result.save(out)
    _print_scene(result, out)
    failures = contract_failures(result.stats)
    for f in failures:
        err_console.print(f"[yellow]quality contract broken:[/] {f}", highlight=False)
    sys.exit(1 if failures else 0)


def _print_scene(result, path) -> None:
    from dualhuman_builder.sim.scenes import describe_scene

    info = describe_scene(result)
    console.print(f"[bold]{path}[/]: {info['summary']}", highlight=False, soft_wrap=True)
    for line in info["lines"]:
        console.print(f"  {line}", highlight=False, soft_wrap=True)


@scene.command("info")
@click.argument("scene_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print parameters, phases and quality as JSON.")
def scene_info(scene_file: Path, as_json: bool):
    """Describe SCENE_FILE: type, actors, timing, phases and its quality measures."""
    from dualhuman_builder.sim.scenes import Scene, describe_scene

    result = Scene.load(scene_file)
    if as_json:
        click.echo(json.dumps(describe_scene(result)["data"], indent=2))
    else:
        _print_scene(result, scene_file)


@scene.command("preview")
@click.argument("scene_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="PNG strip, or .gif for an animation (default: next to SCENE_FILE, .png).")  # fmt: skip
@click.option("--frames", type=click.IntRange(1, 60), default=6, show_default=True, help="How many moments to show.")
@click.option("--contacts/--no-contacts", default=True, show_default=True, help="Paint ground-truth contact vertices yellow.")
@click.option("--spp", type=click.IntRange(1, 1024), default=24, show_default=True, help="Samples per pixel.")
def scene_preview(scene_file: Path, out: Path | None, frames: int, contacts: bool, spp: int):
    """Render the two bodies of SCENE_FILE at a few moments, side by side, with Mitsuba."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.render.preview import render_strip
    from dualhuman_builder.sim.scenes import Scene

    result = Scene.load(scene_file)
    out = out or scene_file.with_suffix(".png")
    with console.status("rendering...") as spinner:
        info = render_strip(result.sequence, get_body_model().faces.cpu().numpy(), out, frames=frames, spp=spp,
                            highlight=result.contact_labels() if contacts else None,
                            progress=lambda m: spinner.update(m))  # fmt: skip
    console.print(f"wrote {out} ({len(info['frames'])} frames, {info['variant']}, {info['seconds']:.1f} s)", highlight=False)


# --------------------------------------------------------------------------------------------- sim
@main.group()
def sim():
    """Simulated devices: suits, trackers and IMUs driven by a ground-truth scene."""


@sim.command("play")
@click.argument("source")
@click.option("--mvn", default="127.0.0.1:9763", show_default=True, help="HOST:PORT for the MVN datagrams of both suits ('' to skip).")
@click.option("--trackers", default="127.0.0.1:8051", show_default=True, help="HOST:PORT for the tracker datagrams ('' to skip).")
@click.option("--xbus", default=None, help="Serial port for the Xbus MTi: 'pty' (prints the path to open) or a pyserial URL/device.")
@click.option("--can", "can_bus", default=None, metavar="INTERFACE:CHANNEL", help="python-can bus for the CAN MTi, e.g. socketcan:vcan0.")
@click.option("--speed", type=float, default=1.0, show_default=True, help="Times real time; 0 means as fast as possible.")
@click.option("--loss", type=click.FloatRange(0, 1), default=0.0, help="Probability a packet is dropped.")
@click.option("--reorder", type=click.FloatRange(0, 1), default=0.0, help="Probability a packet is held back behind later ones.")
@click.option("--duplicate", type=click.FloatRange(0, 1), default=0.0, help="Probability a packet is sent twice.")
@click.option("--corrupt", type=click.FloatRange(0, 1), default=0.0, help="Probability a packet has a byte flipped.")
@click.option("--outage", multiple=True, metavar="START-STOP[@STREAM]",
              help="Silence streams (fnmatch, e.g. 'mvn/1' or 'vive/*') from START to STOP seconds; repeatable.")  # fmt: skip
@click.option("--fault-seed", type=int, default=0, show_default=True, help="Seed of the injected faults.")
def sim_play(source, mvn, trackers, xbus, can_bus, speed, loss, reorder, duplicate, corrupt, outage, fault_seed):
    """Play the devices of SOURCE (sim://TYPE?seed=N, or sim:///path/scene.npz) onto real
    transports in real time (or --speed N times faster), with optional injected faults.

    Example: dualhuman sim play 'sim://handshake?seed=3' --speed 2 --loss 0.01
    """
    import math

    from dualhuman_builder.capture.sources import open_source
    from dualhuman_builder.sim.devices import Faults, Outage
    from dualhuman_builder.sim.play import play_studio

    outages = []
    for text in outage:
        span, _, stream = text.partition("@")
        a, _, b = span.partition("-")
        try:
            outages.append(Outage(float(a), float(b), stream or None))
        except ValueError as e:
            raise click.BadParameter(f"--outage {text!r}: {e}; write START-STOP[@STREAM], e.g. 1.5-2.5@mvn/0") from None
    try:
        faults = Faults(seed=fault_seed, loss=loss, reorder=reorder, duplicate=duplicate, corrupt=corrupt,
                        outages=tuple(outages))  # fmt: skip
    except ValueError as e:
        raise click.BadParameter(str(e)) from None
    with console.status(f"simulating {source}...") as spinner:
        src = open_source(source, progress=lambda m: spinner.update(m))
    try:
        play = play_studio(src.studio, mvn=mvn or None, trackers=trackers or None, xbus=xbus, can_bus=can_bus,
                           speed=math.inf if speed == 0 else speed, faults=faults,
                           log=lambda m: console.print(f"[dim]sim:[/] {m}", highlight=False))  # fmt: skip
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    if play.pty_path:
        console.print(f"Xbus MTi on serial port {play.pty_path}", highlight=False)
    try:
        with play:
            reports = play.join()
    except KeyboardInterrupt:
        console.print("stopped")
        return
    for name, r in reports.items():
        faults_text = ", ".join(f"{k} {v}" for k, v in r.faults.counts().items() if v and k != "sent") or "no faults"
        console.print(f"{name}: sent {r.sent} packets ({r.bytes_sent} bytes) in {r.elapsed_s:.2f} s; {faults_text}",
                      highlight=False)  # fmt: skip
    if play.pty is not None and play.pty.dropped_bytes:
        console.print(f"xbus: {play.pty.dropped_bytes} bytes dropped: nobody read {play.pty_path} fast enough", highlight=False)


# ---------------------------------------------------------------------------------------------
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
    full disk mid-take stops it cleanly: everything before is kept (exit status 1).

    \b
    Examples:
      dualhuman capture --rig rigs/studio.toml --take T001 --duration 60 -w WS
      dualhuman capture --source 'sim://handshake?seed=3' --take sim1 --out sim1.mcap
      dualhuman capture --source suits=mvn+udp://:9763 --actor alice=suits#0 --take T2 --out T2.mcap
    """
    import math

    from rich.live import Live

    from dualhuman_builder.capture.session import capture_take, default_take_path, plan_capture
    from dualhuman_builder.console import live_status_table

    plan = plan_capture(rig_file, sources, actors)
    if out is None:
        if workspace is None:
            raise click.UsageError("say where the take goes: --workspace WS or --out TAKE.mcap")
        out = default_take_path(workspace, take)
    speed = math.inf if sim_speed == 0 else sim_speed
    log = None if quiet else (lambda m: err_console.print(f"[dim]{m}[/]", highlight=False))
    if quiet or not console.is_terminal:
        result = capture_take(plan, out, take=take, duration=duration, workspace=workspace, progress=log,
                              sim_speed=speed, foxglove_hz=foxglove_hz)  # fmt: skip
    else:
        with Live(console=console, refresh_per_second=4, transient=False) as live:
            result = capture_take(plan, out, take=take, duration=duration, workspace=workspace, progress=log,
                                  sim_speed=speed, foxglove_hz=foxglove_hz,
                                  on_status=lambda st: live.update(live_status_table(st)))  # fmt: skip
    counts = result.samples_per_topic
    console.print(f"take {result.take}: {result.duration_s:.1f} s, {sum(counts.values())} samples on {len(counts)} "
                  f"topics, {result.messages} messages -> {result.path}", highlight=False)  # fmt: skip
    for name, st in result.source_stats.items():
        shown = ", ".join(f"{k} {v}" for k, v in sorted(st.items()) if v and k not in ("bytes",))
        console.print(f"  {name}: {shown}", highlight=False)
    for ev in result.events[:20]:
        console.print(f"  [yellow]{ev['source']} {ev['entity']}: {ev['kind']}[/] {ev['message']}", highlight=False)
    if result.error:
        from dualhuman_builder.console import print_error
        from dualhuman_builder.errors import DualhumanError

        print_error(err_console, DualhumanError(result.error, fix="the take is kept up to the failure; "
                                                f"check it with `dualhuman log check {result.path}`"))
        sys.exit(1)


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
                      f"{rep.size} bytes ({rep.lost_bytes} unreadable at the end)", highlight=False)  # fmt: skip
        for topic, n in sorted(rep.per_topic.items()):
            console.print(f"  {topic}: {n}", highlight=False)
        for p in rep.problems:
            console.print(f"  [yellow]problem:[/] {p}", highlight=False)
    sys.exit(0 if rep.ok else 1)


@log.command("repair")
@click.argument("take_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Write the repaired take here (default: in place; the original is kept as NAME.damaged.mcap).")
def log_repair(take_file: Path, out: Path | None):
    """Rebuild a take cut off by a crash, kill -9 or a full disk: everything readable, with a full index."""
    from dualhuman_builder.capture.log.reader import repair_take

    rep = repair_take(take_file, out)
    console.print(f"repaired {rep.path}: {rep.messages} messages kept, {rep.lost_bytes} bytes lost at the end",
                  highlight=False)  # fmt: skip
    if rep.original:
        console.print(f"  original kept as {rep.original}", highlight=False)
    for p in rep.problems:
        console.print(f"  [yellow]problem:[/] {p}", highlight=False)


@log.command("dump")
@click.argument("take_file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--jsonl", is_flag=True, help="One JSON object per line (the only format for now).")
@click.option("--raw", is_flag=True, help="Also dump the raw packets (hex).")
@click.option("--topic", "topics", multiple=True, help="Only topics starting with this; repeatable.")
def log_dump(take_file: Path, jsonl: bool, raw: bool, topics: tuple[str, ...]):
    """Print every decoded sample: source, character or device, device and host timestamps (ns),
    fields in SI units (metres, m/s, m/s^2, rad/s; quaternions x, y, z, w; Y-up world).

    Example: dualhuman log dump T001.mcap --jsonl | head"""
    from dualhuman_builder.capture.log.reader import dump_jsonl

    try:
        dump_jsonl(take_file, sys.stdout, raw=raw, topics=topics)
    except BrokenPipeError:
        sys.stderr.close()


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
      dualhuman replay T001.mcap --to mvn+udp://127.0.0.1:9763 --to vive+udp://127.0.0.1:8051 --speed 1
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
            console.print(f"  not sent (no --to for their kind): {', '.join(rep.skipped_sources)}", highlight=False)
        return
    t = time.perf_counter()
    columns = read_columns(take_file)
    dt = time.perf_counter() - t
    n = sum(c.count for c in columns.values())
    firsts = [int(c.columns["host_time_ns"][0]) for c in columns.values() if c.count]
    lasts = [int(c.columns["host_time_ns"][-1]) for c in columns.values() if c.count]
    span = (max(lasts) - min(firsts)) / 1e9 if firsts else 0.0
    console.print(f"{n} samples over {span:.1f} s of host time, read in {dt:.2f} s", highlight=False)
    for topic, c in sorted(columns.items()):
        console.print(f"  {topic}: {c.count} {c.sample_type}", highlight=False)
    if verify:
        chk = verify_replay(take_file)
        if chk.identical:
            console.print(f"[green]re-decoding the raw packets gives the recorded {chk.samples} samples bit for bit[/]")
        else:
            console.print(f"[red]{chk.mismatches} of {chk.samples} samples differ[/]; first: {chk.first_mismatch}")
            sys.exit(1)


# ---------------------------------------------------------------------------- sync / fuse / fit
def _take_options(f):
    f = click.option("--take", required=True, help="Take name in the workspace (see `dualhuman status WS`).")(f)
    f = click.option("--fps", type=click.FloatRange(min=1.0, max=1000.0), default=30.0, show_default=True,
                     help="Frame rate of the common timeline (and of the fitted bodies).")(f)
    f = click.option("--no-trackers", is_flag=True, help="Ignore the trackers (fusion falls back to the suit's drifting positions; flagged).")(f)
    f = click.option("--no-suit-chain", is_flag=True,
                     help="Do not solve the suit's segment misalignments with the tracker mounts (to see what they buy).")(f)
    f = click.option("--mounts-from", "mounts_from", metavar="TAKE", default=None,
                     help="The session's calibration take (actors bowing, twisting, raising their arms and turning on "
                          "the spot; `sim://calibration` simulates one): each tracker worn there by the same actor on "
                          "the same segment keeps the mount solved there. A take whose actors hardly move then still "
                          "gets its heading and its trackers' offsets right; a tracker strapped again since is found "
                          "and solved afresh. The trackers' lag behind the suits (the session's latencies) is averaged "
                          "with the one measured there, unless it moved by over 3 ms (a warning).")(f)
    f = click.option("--force", is_flag=True, help="Run again even when the stage is up to date.")(f)
    return click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))(f)


@main.command()
@_take_options
def sync(workspace: Path, take: str, fps: float, no_trackers: bool, no_suit_chain: bool, mounts_from: str | None,
         force: bool):  # fmt: skip
    """Put a take's streams on one timeline and calibrate the trackers.

    Per stream: its clock's offset and drift against the host (a robust fit of the lower envelope
    of device-vs-host stamps: delayed packets are rejected). Per tracker: the residual lag against
    the suit segment it is strapped to (cross-correlation of angular speeds) and its mounting
    rotation and offset (least squares, with the suit's heading and position drift, and the
    suit's segment misalignments along each tracker's chain from the pelvis: a suit's limbs sit
    where its measured orientations put them, tens of millimetres off, and the offsets would
    otherwise absorb that). Writes sync.npz and sync.json (estimates with 1-sigma uncertainties).

    An actor who hardly turns a segment (standing still while patted, shaking hands) leaves the
    trackers' mounting rotations and shared offset to where the protocol says they are strapped,
    and a short take measures the trackers' lag less well than a long one; start the session with
    a calibration take and pass it with --mounts-from (mounts and lag carry over).

    \b
    Examples:
      dualhuman sync WS --take T001
      dualhuman sync WS --take T002 --mounts-from T001   # T001: the session's calibration take
    """
    from dualhuman_builder.fit.stages import run_sync
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = run_sync(ws, take, fps=fps, use_trackers=not no_trackers, force=force, log=console.print,
                       suit_chain=not no_suit_chain, mounts_from=mounts_from)  # fmt: skip
        console.print(f"sync {'up to date' if res.skipped else 'done'}: {res.artifacts.get('sync.json')}", highlight=False)


@main.command()
@_take_options
def fuse(workspace: Path, take: str, fps: float, no_trackers: bool, no_suit_chain: bool, mounts_from: str | None,
         force: bool):  # fmt: skip
    """Fuse each actor's suit and trackers into one drift-free skeleton.

    Suit orientations (heading-corrected against the tracker world, each segment turned by the
    misalignment sync solved), positions corrected by the trackers (the drift-free reference);
    tracker jumps rejected, dropouts bridged smoothly. Runs `sync` first if needed.

    Example:  dualhuman fuse WS --take T001
    """
    from dualhuman_builder.fit.stages import run_fuse
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = run_fuse(ws, take, force=force, log=console.print, fps=fps, use_trackers=not no_trackers,
                       suit_chain=not no_suit_chain, mounts_from=mounts_from)  # fmt: skip
        console.print(f"fuse {'up to date' if res.skipped else 'done'}", highlight=False)


@main.command()
@_take_options
@click.option("--no-collision", is_flag=True, help="Fit without the SDF collision term (to see what it removes).")
@click.option("--relaxed-hands", is_flag=True,
              help="Keep anny's relaxed fingers: do not let the collision term open the hands (thumb and fingers).")
@click.option("--exact-contacts", is_flag=True,
              help="Locate the collision contacts at every L-BFGS evaluation instead of holding them through each pass "
                   "(the fallback the default uses where held contacts stall; slower, for comparison).")
@click.option("--window", type=click.IntRange(min=4), default=48, show_default=True, help="Frames optimised together.")
@click.option("--device", default="cpu", show_default=True,
              help="torch device for the fit, e.g. cuda. The CPU is the faster choice even where a GPU is: the fit's "
                   "many small tensor operations gain little there, and a GPU fit runs in one process "
                   "(a 1-minute hug on an H200 machine: 8.5-10.2 frame pairs/s on cuda, 39-51 on its 16 CPUs).")
@click.option("--threads", type=click.IntRange(min=0), default=1, show_default=True,
              help="torch CPU threads during the fit. 1 makes a fit of the same take repeat exactly; more can be "
                   "~10-20 % faster but the result then varies from run to run; 0 keeps torch's own setting.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Processes to fit the take's segments on, this one included (1: only this one). Default: one per "
                   "CPU, no more than there are segments (two windows each) or than leave ~2 GiB of available memory "
                   "each; 1 on a GPU. The result does not depend on it.")
def fit(workspace: Path, take: str, fps: float, no_trackers: bool, no_suit_chain: bool, mounts_from: str | None, force: bool,
        no_collision: bool, relaxed_hands: bool, exact_contacts: bool, window: int, device: str, threads: int,
        workers: int | None):  # fmt: skip
    """Fit both actors' anny bodies to a take, jointly.

    One shape per actor from the suit's segment lengths (and the registered height); per frame a
    closed-form retarget of the segment orientations, refined over windows of frames by L-BFGS on
    orientation, tracker, smoothness, floor and foot-stance terms plus an SDF collision term between
    the two bodies. The suit measures no fingers: where a hand lies on the partner, the collision
    term opens its thumb and fingers (between anny's relaxed hand and flat) before it moves any
    bone. Writes bodies.npz, shapes.json, frames.npz and report.html / report.png.
    Runs `sync` and `fuse` first if needed. The take is fitted in segments of two windows, on
    --workers processes at once; consecutive segments are cross-faded over the frames they share
    (and a seam whose blend leaves the bodies in each other is fitted again).

    Example:  dualhuman fit WS --take T001
    """
    from dualhuman_builder.fit.fitter import FitConfig
    from dualhuman_builder.fit.stages import run_fit
    from dualhuman_builder.workspace import Workspace

    cfg = FitConfig(collision=not no_collision, hand_opening=not relaxed_hands, collision_hold_contacts=not exact_contacts,
                    window=window, device=device, torch_threads=threads)  # fmt: skip
    with Workspace.open(workspace) as ws:
        res = run_fit(ws, take, cfg, force=force, log=console.print, fps=fps, use_trackers=not no_trackers,
                      suit_chain=not no_suit_chain, workers=workers, mounts_from=mounts_from)  # fmt: skip
        console.print(f"fit {'up to date' if res.skipped else 'done'}; report: {res.artifacts.get('report.html')}", highlight=False)


# ---------------------------------------------------------------------------- contacts / render
@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--take", required=True, help="Take name in the workspace (its fit stage must be complete).")
@click.option("--threshold", type=click.FloatRange(min=0.0, max=0.5), default=0.02, show_default=True,
              help="Distance (m) under which a vertex counts as in contact; penetrating vertices always do.")
@click.option("--band", type=click.FloatRange(min=0.001, max=1.0), default=0.05, show_default=True,
              help="Distances (m) are computed and stored within this band of the other body; NaN beyond.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Processes to spread the frames over (1: in this one). Default: one per two CPUs, up to 8, when each "
                   "gets at least 48 frames. The result does not depend on it.")
@click.option("--force", is_flag=True, help="Run again even when the stage is up to date.")
def contacts(workspace: Path, take: str, threshold: float, band: float, workers: int | None, force: bool):
    """Per-vertex contacts between the two fitted bodies, frame by frame (libigl).

    For every frame, the signed distance of each body's vertices to the other body's surface
    (libigl, pseudonormal sign, within --band; frames whose bodies' boxes are farther apart are
    skipped, and a warp BVH picks the vertices and faces libigl must look at), both ways. Writes
    contacts.npz (per-vertex labels, bit-packed; float16 distances; per-frame flag) and contacts.json (region-level contact events: body-part
    pairs with start and end frames, like CHI3D's signatures; counts; speed).

    Example:  dualhuman contacts WS --take T001
    """
    from dualhuman_builder.contacts.stage import run_contacts
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = run_contacts(ws, take, threshold_m=threshold, band_m=band, force=force, log=console.print, workers=workers)
        console.print(f"contacts {'up to date' if res.skipped else 'done'}: {res.artifacts.get('contacts.json')}", highlight=False)


@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--take", required=True, help="Take name in the workspace (its fit stage must be complete).")
@click.option("--views", type=click.IntRange(min=1, max=256), default=8, show_default=True, help="Cameras on the ring.")
@click.option("--size", type=click.IntRange(min=16, max=8192), default=512, show_default=True, help="Image width and height (pixels).")
@click.option("--spp", type=click.IntRange(min=1), default=16, show_default=True, help="Samples per pixel of the RGB images.")
@click.option("--radius", type=click.FloatRange(min=0.1), default=3.0, show_default=True, help="Ring radius (m) around the pair.")
@click.option("--height", type=float, default=1.4, show_default=True, help="Camera height above the floor (m).")
@click.option("--fov", type=click.FloatRange(min=1.0, max=170.0), default=50.0, show_default=True, help="Horizontal field of view (degrees).")
@click.option("--jitter-seed", type=int, default=None, help="Perturb each view's azimuth, radius and height with this seed.")
@click.option("--rig", "rig_file", type=click.Path(dir_okay=False, exists=True, path_type=Path), default=None,
              help="JSON camera rig file: explicit cameras instead of the ring (see the README).")
@click.option("--template", default="studio", show_default=True, help="Scene template in render_templates/ (name or path).")
@click.option("--every", type=click.IntRange(min=1), default=1, show_default=True, help="Render every N-th frame.")
@click.option("--max-frames", type=click.IntRange(min=1), default=None, help="Render at most this many frames.")
@click.option("--variant", default=None, help="Mitsuba variant (default: cuda_ad_rgb, else llvm_ad_rgb, else scalar_rgb).")
@click.option("--no-sheet", is_flag=True, help="Do not draw the contact sheet afterwards.")
@click.option("--force", is_flag=True, help="Render again even when the stage is up to date.")
def render(workspace: Path, take: str, views: int, size: int, spp: int, radius: float, height: float, fov: float,
           jitter_seed: int | None, rig_file: Path | None, template: str, every: int, max_frames: int | None,
           variant: str | None, no_sheet: bool, force: bool):  # fmt: skip
    """Render the fitted pair from a ring of cameras with Mitsuba 3, with full ground truth.

    Per view and frame: RGB (sRGB PNG), depth (EXR, float32 camera z in metres), instance mask (PNG:
    0 background, 1 and 2 the actors); per render: 2D keypoints of both actors (22 joints and COCO)
    with per-joint visibility from a depth test, cameras (K and world-to-camera R|t, OpenCV) and
    visibility statistics. The scene is built once and only vertex positions change per frame. An
    interrupted render (say, a full disk) resumes from the last complete frame when run again.
    Then draws contact_sheet.png (views x frames with masks and keypoints, and the contacts).

    Example:  dualhuman render WS --take T001 --views 8 --size 512
    """
    from dualhuman_builder.render.sheet import run_sheet
    from dualhuman_builder.render.stage import run_render
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = run_render(ws, take, views=views, size=size, spp=spp, radius_m=radius, height_m=height, fov_deg=fov,
                         jitter_seed=jitter_seed, rig_file=rig_file, template=template, every=every, max_frames=max_frames,
                         variant=variant, force=force, log=console.print)  # fmt: skip
        console.print(f"render {'up to date' if res.skipped else 'done'}: {ws.artifact_dir('render', take)}", highlight=False)
        if not no_sheet:
            sheet = run_sheet(ws, take, force=force, log=console.print)
            console.print(f"contact sheet: {sheet.artifacts.get('contact_sheet.png')}", highlight=False)


# ---------------------------------------------------------------------------- annotate
@main.group()
def annotate():
    """Interaction labels and descriptions: round-trip them through any annotation tool.

    \b
      dualhuman annotate vocabulary [WS]             the label names you may use
      dualhuman annotate export WS labels.csv        every take and sequence, annotated or blank
      dualhuman annotate import WS labels.csv        read them back (CSV or JSON Lines)

    A label record: labels from the vocabulary (CHI3D's eight types and NTU-120's mutual actions,
    extended by WS/labels.toml), actor and reactor for one-sided interactions, a symmetric flag,
    several free-text descriptions, the annotator and the time. The export stores them per
    sequence (text.json, with a multi-hot vector over labels.json).
    """


@annotate.command("vocabulary")
@click.argument("workspace", required=False, type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.option("--json", "as_json", is_flag=True, help="Print labels.json as the export writes it.")
def annotate_vocabulary(workspace: Path | None, as_json: bool):
    """List the interaction labels (the built-in vocabulary, plus WORKSPACE/labels.toml if given).

    Example:  dualhuman annotate vocabulary WS
    """
    from dualhuman_builder.errors import WorkspaceError
    from dualhuman_builder.export.labels import load_vocabulary

    try:
        vocab = load_vocabulary(workspace)
    except ValueError as e:
        raise WorkspaceError(str(e), path=workspace) from None
    if as_json:
        click.echo(json.dumps(vocab.as_dict(), indent=1))
        return
    for i, lab in enumerate(vocab.labels):
        side = "one-sided" if lab.one_sided else "symmetric"
        console.print(f"{i:3d}  {lab.name:<20} {side:<10} {lab.description}  [dim]({', '.join(lab.sources)})[/]",
                      highlight=False, soft_wrap=True)  # fmt: skip


@annotate.command("export")
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("file", required=False, type=click.Path(dir_okay=False, path_type=Path))
@click.option("--format", "fmt", type=click.Choice(["csv", "jsonl"]), default=None,
              help="File format (default: from FILE's extension; JSON Lines on standard output).")
@click.option("--no-blank", is_flag=True, help="Only stored annotations, no blank rows for unannotated takes.")
def annotate_export(workspace: Path, file: Path | None, fmt: str | None, no_blank: bool):
    """Write the annotations of WORKSPACE to FILE (.csv or .jsonl; standard output without FILE):
    every stored annotation, and a blank row for each take and sequence that has none yet, to be
    filled in and imported back.

    CSV columns: take, sequence, labels (';'-separated), actor, reactor, symmetric, annotator,
    annotated_at, text_1, text_2, text_3, ...

    Example:  dualhuman annotate export WS labels.csv
    """
    from dualhuman_builder.export.annotate import export_annotations
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace, readonly=True) as ws:
        text, n = export_annotations(ws, file, fmt, blank=not no_blank)
    if file is None:
        click.echo(text, nl=False)
    else:
        console.print(f"{n} row(s) written to {file}", highlight=False)


@annotate.command("import")
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("file", type=click.Path(dir_okay=False, exists=True, path_type=Path))
@click.option("--annotator", default=None, help="Annotator name for rows whose annotator column is empty.")
@click.option("--skip-invalid", is_flag=True, help="Import the valid rows and list the invalid ones (default: import nothing).")
def annotate_import(workspace: Path, file: Path, annotator: str | None, skip_invalid: bool):
    """Read annotations from FILE (.csv or .jsonl, UTF-8) into WORKSPACE's catalog.

    The whole file is checked first: takes and sequences exist, labels are in the vocabulary,
    actor and reactor are actors of the take, the text is UTF-8. A row replaces the stored
    annotation of the same take, sequence and annotator; blank rows are skipped. The next
    `dualhuman export` carries the labels into the dataset.

    Example:  dualhuman annotate import WS labels.csv --annotator alice
    """
    from dualhuman_builder.export.annotate import import_annotations
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = import_annotations(ws, file, annotator=annotator, skip_invalid=skip_invalid)
    for line, msg in res["invalid"]:
        console.print(f"[yellow]skipped[/] line {line}: {msg}", highlight=False)
    console.print(f"{res['imported']} annotation(s) imported from {file} ({res['blank']} blank, "
                  f"{len(res['invalid'])} invalid row(s) skipped)", highlight=False)  # fmt: skip


# ---------------------------------------------------------------------------- export
class _ExportGroup(click.Group):
    """`dualhuman export WS OUT` builds; `dualhuman export verify|shards ...` are subcommands."""

    def resolve_command(self, ctx, args):
        if args and args[0] not in self.commands and not args[0].startswith("-"):
            args = ["build", *args]
        return super().resolve_command(ctx, args)


@main.group(cls=_ExportGroup)
def export():
    """The training-ready dataset: build it, verify it, shard it, convert it.

    \b
      dualhuman export WS OUT                every fitted take of WS -> the dataset folder OUT
      dualhuman export verify OUT            checksums, schema, splits, shapes, NaNs
      dualhuman export shards OUT DIR        WebDataset tar shards of a split, for streaming
      dualhuman export interhuman OUT DEST   InterGen's InterHuman layout (two persons, 30 fps)
      dualhuman export humanml3d OUT DEST    HumanML3D's layout (one motion per person, 20 fps)
    """


@export.command("build")
@click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("out", type=click.Path(file_okay=False, path_type=Path))
@click.option("--take", "takes", multiple=True, help="Export only this take (repeatable; default: every fitted take).")
@click.option("--split", "split_ratio", type=click.FloatRange(min=0.0, max=1.0, min_open=True), default=0.75,
              show_default=True, help="Share of sequences in the train split (the rest is test).")
@click.option("--subject-disjoint", is_flag=True, help="No performer in both splits.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seed of the split.")
@click.option("--strict", is_flag=True, help="Fail when a take lacks a stage instead of exporting what is complete.")
def export_build(workspace: Path, out: Path, takes: tuple[str, ...], split_ratio: float, subject_disjoint: bool, seed: int,
                 strict: bool):  # fmt: skip
    """Export every fitted take of WORKSPACE as a dataset folder OUT.

    Per sequence: both actors' anny parameters and joints, the 269-dim motion features, contacts
    (bit-packed labels, distances, region events), labels and texts, cameras and renders; at the
    top a manifest (versions, units, axes, SHA-256 of every file), a schema of every array, seeded
    train/test splits, feature mean/std and a dataset card (README.md). Re-running completes a
    partial export and rewrites only what changed.

    Example:  dualhuman export WS WS/export
    """
    from dualhuman_builder.export.collect import run_export
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace, readonly=True) as ws:
        m = run_export(ws, out, list(takes) or None, strict=strict, split_ratio=split_ratio,
                       subject_disjoint=subject_disjoint, seed=seed, log=console.print)  # fmt: skip
    console.print(f"exported {len(m['sequences'])} sequence(s) to {out}; check it with `dualhuman export verify {out}`",
                  highlight=False)  # fmt: skip


@export.command("verify")
@click.argument("out", type=click.Path(file_okay=False, exists=True, path_type=Path))
def export_verify(out: Path):
    """Check an exported dataset: every file's SHA-256 against the manifest, arrays against the
    schema (shapes, dtypes, no NaN), splits disjoint and complete, every sequence has what the
    manifest promises. Never unpickles. Exit status 1 when a problem is found.

    Example:  dualhuman export verify WS/export
    """
    from dualhuman_builder.export.verify import verify_export

    problems = verify_export(out)
    for p in problems:
        console.print(f"[red]problem[/]: {p}", highlight=False)
    if problems:
        sys.exit(1)
    console.print(f"[green]{out}: verified[/]", highlight=False)


@export.command("shards")
@click.argument("out", type=click.Path(file_okay=False, exists=True, path_type=Path))
@click.argument("shard_dir", type=click.Path(file_okay=False, path_type=Path))
@click.option("--split", type=click.Choice(["train", "test", "all"]), default="train", show_default=True)
@click.option("--max-mb", type=click.FloatRange(min=0.001), default=256.0, show_default=True, help="Largest shard size (MiB).")
def export_shards(out: Path, shard_dir: Path, split: str, max_mb: float):
    """Write a split of the export OUT as WebDataset tar shards into SHARD_DIR (one sample per
    sequence: motion, contacts, events, text, cameras, keypoints).

    Example:  dualhuman export shards WS/export WS/shards --split train
    """
    from dualhuman_builder.export.shards import write_shards

    paths = write_shards(out, shard_dir, max_bytes=int(max_mb * 2**20), split=split)
    console.print(f"{len(paths)} shard(s) in {shard_dir}", highlight=False)


def _convert(layout: str, out: Path, dest: Path, split: str, label_texts: bool) -> None:
    from dualhuman_builder.export import convert

    try:
        doc = getattr(convert, f"to_{layout}")(out, dest, split=split, label_texts=label_texts)
    except ValueError as e:
        raise click.UsageError(str(e)) from None
    c, unit = doc["counts"], "motions" if "motions" in doc else "sequences"
    per = f" = {doc['motions']} motions" if "motions" in doc else ""
    console.print(f"{layout}: {doc['sequences_converted']} sequence(s){per} ({c['train']} train, {c['test']} test {unit}), "
                  f"{len(doc['skipped'])} skipped, {len(doc['texts_from_labels'])} captioned from labels -> {dest}",
                  highlight=False, soft_wrap=True)  # fmt: skip


_CONVERT_OPTIONS = [
    click.argument("out", type=click.Path(file_okay=False, exists=True, path_type=Path)),
    click.argument("dest", type=click.Path(file_okay=False, path_type=Path)),
    click.option("--split", type=click.Choice(["all", "train", "test"]), default="all", show_default=True,
                 help="Convert only this split of the export."),
    click.option("--label-texts/--no-label-texts", default=True, show_default=True,
                 help="Caption a sequence without text from its labels ('two people interact: <label>.'); off: skip it."),
]  # fmt: skip


def _convert_options(f):
    for deco in reversed(_CONVERT_OPTIONS):
        f = deco(f)
    return f


@export.command("interhuman")
@_convert_options
def export_interhuman(out: Path, dest: Path, split: str, label_texts: bool):
    """Convert the export OUT to InterGen's InterHuman layout in DEST (30 fps), so InterGen's
    dataloader reads it unchanged (DATA_ROOT = DEST).

    Writes motions_processed/person1|person2/<id>.npy (InterHuman's raw (T, 492) per-frame joints and
    6D rotations, Z up, person a = person1), features/p1|p2/<id>.npy (the 262-dim features),
    annots/<id>.txt (three or more sentences), train/val/test.txt (also under split/; val = test),
    ignore_list.txt, global_mean/std.npy, and conversion.json (the per-sequence transform back to the
    world frame, skipped sequences with reasons).

    Example:  dualhuman export interhuman WS/export WS/interhuman
    """
    _convert("interhuman", out, dest, split, label_texts)


@export.command("humanml3d")
@_convert_options
def export_humanml3d(out: Path, dest: Path, split: str, label_texts: bool):
    """Convert the export OUT to HumanML3D's layout in DEST (20 fps, one motion per person: <id>_a,
    <id>_b), for single-person text-to-motion code (T2M, MDM, ...).

    Writes new_joint_vecs/<name>.npy (T-1, 263), new_joints/<name>.npy (T-1, 22, 3) canonical,
    texts/<name>.txt (caption#tokens#0.0#0.0; tokens are lowercased words tagged OTHER, not spaCy's
    lemmas and POS), Mean.npy/Std.npy over the train motions, train/val/test/all.txt (val = test),
    and conversion.json.

    Example:  dualhuman export humanml3d WS/export WS/humanml3d
    """
    _convert("humanml3d", out, dest, split, label_texts)


if __name__ == "__main__":
    main()

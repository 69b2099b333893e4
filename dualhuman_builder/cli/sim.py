"""`dualhuman scene` and `dualhuman sim`: ground-truth scenes and simulated devices."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, err_console, main


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


#: The scene types (``dualhuman_builder.sim.scenes.ALL_TYPES``, spelled out so that --help imports nothing heavy;
#: tests/cli/test_cli.py checks they agree).
SCENE_TYPES = ("handshake", "hug", "high_five", "push", "pat_on_back", "dance_turn", "calibration", "session")
_scene_type_option = click.option(
    "--type", "scene_type", type=click.Choice(SCENE_TYPES), default="handshake", show_default=True, metavar="TYPE",
    help=f"One of {', '.join(SCENE_TYPES)}. The interaction; or 'calibration', the calibration motion of a studio day (the actors apart, turning every "
         "tracked segment: see `dualhuman sync --mounts-from`); or 'session', a long take chaining the interactions "
         "with walking and idling between them (its length: --duration, a minute by default).")  # fmt: skip


@main.group()
def scene():
    """Ground-truth two-person interaction scenes: make, inspect, preview.

    A scene is two anny bodies of different shapes performing a close interaction from
    keyframes and inverse kinematics, with ground-truth vertices and contacts (signed distance
    between the meshes). Every later stage is measured against it.
    """


@scene.command("make")
@_scene_type_option
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
    from dualhuman_builder.sim.generate import generate_scene
    from dualhuman_builder.sim.scenes import SceneContractError, SceneParams, contract_failures

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
            result = generate_scene(params, log=lambda m: spinner.update(m))
    except SceneContractError:
        raise  # no draw met the contract: printed with its fix, exit 1
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


#: The device error presets (``dualhuman_builder.sim.presets.PRESETS``, spelled out so that --help imports nothing
#: heavy; tests/sim/test_presets.py checks they agree).
PRESETS = ("ideal", "realistic")


def _with_preset(source: str, preset: str | None) -> str:
    """``source`` with ``preset=PRESET`` in its query (a sim:// URL); unchanged when ``preset`` is None."""
    from urllib.parse import parse_qsl, urlsplit

    if preset is None:
        return source
    parts = urlsplit(source)
    if parts.scheme != "sim":
        raise click.BadParameter(f"--preset applies to sim:// sources, not {source!r}", param_hint="--preset")
    given = dict(parse_qsl(parts.query, keep_blank_values=True)).get("preset")
    if given is not None:
        if given != preset:
            raise click.BadParameter(f"{source!r} already says preset={given}", param_hint="--preset")
        return source
    return f"{source}{'&' if parts.query else '?'}preset={preset}"


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
@click.option("--preset", type=click.Choice(PRESETS), default=None,
              help="Device errors: 'ideal' (the default) or 'realistic' (every error drawn per take within published "
                   "ranges; docs/guides/simulation-presets.md). The same as preset=... in SOURCE.")  # fmt: skip
def sim_play(source, mvn, trackers, xbus, can_bus, speed, loss, reorder, duplicate, corrupt, outage, fault_seed,
             preset):  # fmt: skip
    """Play the devices of SOURCE (sim://TYPE?seed=N, or sim:///path/scene.npz) onto real
    transports in real time (or --speed N times faster), with optional injected faults.

    Example: dualhuman sim play 'sim://handshake?seed=3' --speed 2 --loss 0.01 --preset realistic
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
    source = _with_preset(source, preset)
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


@sim.command("take")
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
@click.option("--take", required=True, help="Take name (letters, digits, - and _), e.g. T001.")
@_scene_type_option
@click.option("--seed", type=int, default=0, show_default=True, help="Seeds the scene's variations and the device errors.")
@click.option("--fps", type=float, default=30.0, show_default=True, help="Frames per second of the ground truth.")
@click.option("--sequence", default=None, help="Name of the take's one sequence (default: the scene type).")
@click.option("--speed", type=click.FloatRange(min=0.1, max=20.0), default=1.0, show_default=True,
              help="The devices play this many times faster than real time while recorded.")
@click.option("--preset", type=click.Choice(PRESETS), default="ideal", show_default=True,
              help="Device errors: 'ideal' (the simulators' defaults) or 'realistic' (every error drawn per take within "
                   "published ranges; docs/guides/simulation-presets.md).")
@click.option("--force", is_flag=True, help="Run the stages again even when they are up to date.")
def sim_take(workspace: Path, take: str, scene_type: str, seed: int, fps: float, sequence: str | None, speed: float,
             preset: str, force: bool):  # fmt: skip
    """Simulate a take into WORKSPACE (created if missing): its scene, devices and capture stages.

    A generated ground-truth scene of the two simulated actors sim-a (1.68 m) and sim-b (1.82 m),
    registered with the rig sim.toml if the workspace lacks them; the suits, trackers and IMUs of
    rigs/sim.toml simulated from it; and their recording through real loopback transports, checked
    and replayed bit for bit. The take then goes through the rest of the pipeline like a recorded
    one (`dualhuman fit WS --take T`). Run again, it does nothing.

    \b
    Example:
      dualhuman sim take WS --take CAL --type calibration --seed 3
      dualhuman sim take WS --take T001 --type hug --seed 3
      dualhuman sim take WS --take T002 --type hug --seed 3 --preset realistic
      dualhuman fit WS --take T001 --mounts-from CAL
    """
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.sim.stage import DEFAULT_ACTORS, ensure_actors, simulate_take
    from dualhuman_builder.workspace import Workspace

    with Workspace.init(workspace) as ws:
        ws.add_rig(RIGS_DIR / "sim.toml")
        shapes = ensure_actors(ws, DEFAULT_ACTORS, log=console.print)
        params = {"type": scene_type, "seed": seed, "fps": fps}
        ran = simulate_take(ws, take, sequence or scene_type, params, DEFAULT_ACTORS, shapes, speed=speed, force=force,
                            log=console.print, preset=preset)  # fmt: skip
        for stage, res in ran.items():
            console.print(f"{stage}: {'up to date' if res.skipped else 'done'}", highlight=False)


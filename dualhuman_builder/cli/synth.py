"""`dualhuman synth`: a varied synthetic dataset generated into a workspace."""

from __future__ import annotations

import sys
from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main

#: The interaction types (``dualhuman_builder.sim.scenes.SCENE_TYPES``, spelled out so that --help imports nothing
#: heavy; tests/sim/test_synth.py checks they agree).
SYNTH_TYPES = ("handshake", "hug", "high_five", "push", "pat_on_back", "dance_turn")
#: ``dualhuman_builder.sim.scenes.MAX_DRAWS``, spelled out for the same reason (checked there too).
MAX_DRAWS = 8


def _names(ctx, param, value: str | None) -> tuple[str, ...] | None:
    if value is None:
        return None
    return tuple(s.strip() for s in value.split(",") if s.strip())


@main.command()
@click.argument("workspace", type=click.Path(file_okay=False, path_type=Path))
@click.option("--takes", type=int, required=True, help="How many takes to plan and make.")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seeds every draw: the same seed gives the same plan.")
@click.option("--types", default=None, callback=_names, metavar="A,B",
              help=f"Interaction types to draw from (default: all of {', '.join(SYNTH_TYPES)}).")
@click.option("--preset", type=click.Choice(["ideal", "realistic", "mixed"]), default="ideal", show_default=True,
              help="Device errors of each studio day: 'mixed' gives half the days 'realistic' and the rest 'ideal' "
                   "(docs/guides/simulation-presets.md).")
@click.option("--fps", type=float, default=30.0, show_default=True, help="Frames per second of the ground truth.")
@click.option("--long-share", type=float, default=0.1, show_default=True,
              help="Share of the takes that are long 'session' takes chaining interactions.")
@click.option("--long-duration", type=float, default=60.0, show_default=True, help="Seconds of each long take.")
@click.option("--takes-per-day", type=int, default=6, show_default=True,
              help="Takes of one studio day: one pair, one draw of the devices (so one set of tracker mounts) "
                   "and one calibration take, whose mounts the day's takes are synced with. 1 gives every take "
                   "its own pair.")
@click.option("--actors", "pool", type=int, default=None,
              help="Size of the actor pool (default: two per studio day, 4 to 32).")
@click.option("--hold-out-actors", type=int, default=0, show_default=True,
              help="Put every take of this many drawn actors in the test split (the rest in train).")
@click.option("--hold-out-types", default=None, callback=_names, metavar="A,B",
              help="Put every take of these types (and every long take) in the test split.")
@click.option("--path", "way", type=click.Choice(["full", "ground-truth"]), default="full", show_default=True,
              help="full: scene, devices and capture of each take (then `dualhuman run WS`); ground-truth: scene "
                   "straight to the export (--export), no devices and no fit.")
@click.option("--export", "export_dir", type=click.Path(file_okay=False, path_type=Path), default=None,
              help="Export folder: required with --path ground-truth; with --path full, the takes fitted so far "
                   "are exported with the plan's split.")
@click.option("--include-flagged", is_flag=True,
              help="With --path full --export: export takes the quality gates flagged too.")
@click.option("--speed", type=float, default=1.0, show_default=True,
              help="The simulated devices play this many times faster than real time while recorded (full path): to "
                   "test the transports; above 1 the host clock runs slower than the devices' and the sync cannot "
                   "align the takes, so keep 1 for data to fit.")
@click.option("--render", is_flag=True,
              help="With --path ground-truth: render each scene from a ring of cameras (RGB, depth, masks, "
                   "keypoints) into the export, as a fitted take's renders, with the image models' targets.")
@click.option("--render-size", type=int, default=128, show_default=True, help="With --render: image side in pixels.")
@click.option("--render-views", type=int, default=4, show_default=True, help="With --render: cameras on the ring.")
@click.option("--render-every", type=int, default=5, show_default=True, help="With --render: render every N-th frame.")
@click.option("--render-spp", type=int, default=4, show_default=True, help="With --render: samples per pixel.")
@click.option("--max-draws", type=click.IntRange(1, 64), default=MAX_DRAWS, show_default=True,
              help="With --path ground-truth: the most draws of a scene's variation before its take fails. A scene's "
                   "generation is deterministic: a failed take is recorded (WS/synth/scenes/TAKE-gN.failed.json) and "
                   "not drawn again on resume, unless asked for with more draws.")
@click.option("--jobs", type=click.IntRange(min=1), default=None,
              help="With --path ground-truth: worker processes making scenes and renders at once. Default: one per CPU "
                   "within the available memory at 2 GiB each (1 makes them in this process).")
@click.option("--plan-only", is_flag=True, help="Print the plan's summary and write WS/synth.json; make nothing.")
def synth(workspace: Path, takes: int, seed: int, types, preset: str, fps: float, long_share: float,
          long_duration: float, takes_per_day: int, pool: int | None, hold_out_actors: int, hold_out_types, way: str,
          export_dir: Path | None, include_flagged: bool, speed: float, render: bool, render_size: int,
          render_views: int, render_every: int, render_spp: int, max_draws: int, jobs: int | None,
          plan_only: bool):  # fmt: skip
    """Generate a varied synthetic dataset of TAKES simulated takes into WORKSPACE (created if missing).

    The plan (WORKSPACE/synth.json) is drawn from the seed: an actor pool over statures, genders
    and build; studio days, each with a pair, a draw of the devices and their errors, and a
    calibration take; each take's interaction type, tempo, approach distance and split, and a
    share of long takes. `dualhuman run` syncs each take with its day's tracker mounts. Run again with the same arguments, it resumes (takes made
    before are skipped); with other arguments, it refuses. One line per take; exits 1 when a
    take's scene met no quality contract.

    \b
    Examples:
      dualhuman synth WS --takes 24 --seed 1 --hold-out-actors 2
      dualhuman run WS
      dualhuman synth WS --takes 24 --seed 1 --hold-out-actors 2 --export OUT
      dualhuman synth GT --takes 200 --path ground-truth --export OUT
      dualhuman synth GT --takes 200 --path ground-truth --export OUT --render
    """
    from rich.markup import escape

    from dualhuman_builder.batch.synth import make_synthetic
    from dualhuman_builder.sim.synth import SynthOptions, describe_plan, plan_synthetic

    options = SynthOptions(takes=takes, seed=seed, types=types or SYNTH_TYPES, preset=preset, fps=fps,
                           long_share=long_share, long_duration=long_duration, takes_per_day=takes_per_day, actors=pool,
                           hold_out_actors=hold_out_actors, hold_out_types=hold_out_types or (), speed=speed,
                           render=render, render_size=render_size, render_views=render_views, render_every=render_every,
                           render_spp=render_spp, max_draws=max_draws)  # fmt: skip
    plan = plan_synthetic(options)
    for line in describe_plan(plan, way):
        console.print(escape(line), highlight=False)
    settings = options.render_settings()
    if settings is not None:
        console.print(f"renders: {settings['views']} views of {settings['size']} px, every {settings['every']} frame(s), "
                      f"{settings['spp']} spp, ring {settings['radius_m']:g} m, {settings['height_m']:g} m high, "
                      f"{settings['fov_deg']:g} deg", highlight=False)  # fmt: skip
    if plan_only:
        from dualhuman_builder.sim.synth import record_plan
        from dualhuman_builder.workspace import Workspace

        with Workspace.init(workspace) as ws:
            record_plan(ws.root, plan)
        console.print(f"plan written to {workspace / 'synth.json'}", highlight=False)
        return

    if jobs is not None and way != "ground-truth" and jobs > 1:
        raise click.UsageError("--jobs makes ground-truth takes at once; the full path's stages run at once in "
                               "`dualhuman run WS --workers N`")  # fmt: skip

    def say(line: str) -> None:
        console.print(escape(line), highlight=False, soft_wrap=True)

    if console.is_terminal:
        with console.status("planning...") as spinner:
            result = make_synthetic(workspace, options, path=way, export=export_dir, include_flagged=include_flagged, jobs=jobs,
                                    log=lambda m: spinner.update(escape(str(m)[:100])), progress=say)  # fmt: skip
    else:
        result = make_synthetic(workspace, options, path=way, export=export_dir, include_flagged=include_flagged, jobs=jobs,
                                log=lambda m: None, progress=say)  # fmt: skip
    days = f" (and {len(result.calibrations)} studio days' calibration takes)" if result.calibrations else ""
    console.print(f"{len(result.made)} made, {len(result.skipped)} made before, {len(result.failed)} failed{days} "
                  f"in {result.seconds:.0f} s", highlight=False)  # fmt: skip
    if result.manifest is not None:
        c = result.manifest["counts"]
        console.print(f"export {export_dir}: {c['sequences']} sequences ({c['train']} train, {c['test']} test), "
                      f"source {result.manifest.get('source')}", highlight=False)  # fmt: skip
    elif way == "full":
        console.print(f"next: `dualhuman run {workspace}`", highlight=False)
    if result.failed:
        sys.exit(1)

"""`dualhuman sync`, `fuse`, `fit`, `contacts`, `render`, `sheet`: the per-take stages.

Each publishes its new result only once it is complete (a failed run keeps the previous one) and
says which runs that read it are stale now (:mod:`dualhuman_builder.workspace.runner`)."""

from __future__ import annotations

from pathlib import Path

import click

from dualhuman_builder.cli.app import console, main
from dualhuman_builder.fit.config import SOLVERS, TAKE_STEPS


def _made_stale(res) -> None:
    """Say which runs a stage's new result made stale (they run again when their commands do)."""
    from rich.markup import escape

    from dualhuman_builder.workspace.workspace import printable

    if res.made_stale:
        runs = ", ".join(f"{stage} of {take}" + (f"/{seq}" if seq else "") for take, seq, stage in res.made_stale)
        console.print(f"[yellow]now stale[/] (they read this result; run them again): {escape(printable(runs))}",
                      highlight=False, soft_wrap=True)  # fmt: skip


def _take_options(f):
    f = click.option("--take", required=True, help="Take name in the workspace (see `dualhuman status WS`).")(f)
    f = click.option("--fps", type=click.FloatRange(min=1.0, max=1000.0), default=30.0, show_default=True,
                     help="Frame rate of the common timeline (and of the fitted bodies).")(f)
    f = click.option("--no-trackers", is_flag=True, help="Ignore the trackers (fusion falls back to the suit's drifting positions; flagged).")(f)
    f = click.option("--no-suit-chain", is_flag=True,
                     help="Do not solve the suit's segment misalignments with the tracker mounts (to see what they buy).")(f)
    f = click.option("--mounts-from", "mounts_from", metavar="TAKE", default=None,
                     help="The studio day's calibration take (actors bowing, twisting, raising their arms and turning on "
                          "the spot; `sim://calibration` simulates one). Each tracker worn there by the same actor on "
                          "the same segment keeps the mount solved there (one strapped again since is solved afresh), "
                          "and the trackers' lag behind the suits is averaged with the one measured there unless the "
                          "two differ by over 3 ms (then a warning). For takes whose actors hardly move.")(f)
    f = click.option("--force", is_flag=True,
                     help="Run again even when the stage is up to date; the stages that read it become stale.")(f)
    return click.argument("workspace", type=click.Path(file_okay=False, exists=True, path_type=Path))(f)


@main.command()
@_take_options
def sync(workspace: Path, take: str, fps: float, no_trackers: bool, no_suit_chain: bool, mounts_from: str | None,
         force: bool):  # fmt: skip
    """Put a take's streams on one timeline and calibrate the trackers.

    Per stream: its clock's offset and drift against the host (delayed packets rejected). Per
    tracker: its lag behind the suit segment it is strapped to, and its mounting rotation and
    offset on that segment, solved together with the suit's heading and position drift and
    (unless --no-suit-chain) the suit's segment misalignments along the tracker's chain from the
    pelvis. Writes sync.npz and sync.json (estimates with 1-sigma uncertainties).

    A take whose actors hardly turn a segment (standing still, shaking hands) leaves the mounts
    to where the protocol says the trackers are strapped, and a short take measures the lag
    poorly: start the studio day with a calibration take (CAL below) and pass it with
    --mounts-from.

    \b
    Examples:
      dualhuman sync WS --take T001
      dualhuman sync WS --take T002 --mounts-from CAL
    """
    from dualhuman_builder.sync.stage import run_sync
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = run_sync(ws, take, fps=fps, use_trackers=not no_trackers, force=force, log=console.print,
                       suit_chain=not no_suit_chain, mounts_from=mounts_from)  # fmt: skip
        console.print(f"sync {'up to date' if res.skipped else 'done'}: {res.artifacts.get('sync.json')}", highlight=False)
        _made_stale(res)


@main.command()
@_take_options
def fuse(workspace: Path, take: str, fps: float, no_trackers: bool, no_suit_chain: bool, mounts_from: str | None,
         force: bool):  # fmt: skip
    """Fuse each actor's suit and trackers into one drift-free skeleton.

    Suit orientations (heading-corrected against the tracker world, each segment turned by the
    misalignment sync solved), positions corrected by the trackers (the drift-free reference);
    tracker jumps rejected, dropouts bridged smoothly. Runs `sync` first if needed (or stale).

    Example:  dualhuman fuse WS --take T001
    """
    from dualhuman_builder.fit.stage import run_fuse
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = run_fuse(ws, take, force=force, log=console.print, fps=fps, use_trackers=not no_trackers,
                       suit_chain=not no_suit_chain, mounts_from=mounts_from)  # fmt: skip
        console.print(f"fuse {'up to date' if res.skipped else 'done'}", highlight=False)
        _made_stale(res)


@main.command()
@_take_options
@click.option("--no-collision", is_flag=True, help="Fit without the SDF collision term (to see what it removes).")
@click.option("--relaxed-hands", is_flag=True,
              help="Keep anny's relaxed fingers: do not let the collision term open the hands (thumb and fingers).")
@click.option("--exact-contacts", is_flag=True,
              help="Locate the collision contacts at every L-BFGS evaluation instead of holding them through each pass "
                   "(the default falls back to this where held contacts stall; slower; for comparison).")
@click.option("--window", type=click.IntRange(min=4), default=48, show_default=True, help="Frames optimised together.")
@click.option("--solver", type=click.Choice(SOLVERS), default="windows", show_default=True,
              help="windows: windows of --window frames one after another, segments on --workers processes (the "
                   "faster on long takes on a CPU); take: the whole take as one problem in one process, with a "
                   "per-frame collision schedule, about as accurate on the accuracy tables (--window and "
                   "--workers do not apply).")
@click.option("--take-step", type=click.Choice(TAKE_STEPS), default="shared", show_default=True,
              help="With --solver take, how its collision passes step: shared, one L-BFGS run over every moving "
                   "frame; runs, each run of moving frames its own L-BFGS run (own step length), all evaluated "
                   "at once.")
@click.option("--device", default="cpu", show_default=True,
              help="torch device for the fit, e.g. cuda. Prefer the CPU even where a GPU is: the fit's many small "
                   "tensor operations gain little on a GPU, and a GPU fit runs in one process (no --workers).")
@click.option("--threads", type=click.IntRange(min=0), default=1, show_default=True,
              help="torch CPU threads during the fit. 1 makes a fit of the same take repeat exactly; more may "
                   "be faster, but the result then varies from run to run; 0 keeps torch's own setting.")
@click.option("--workers", type=click.IntRange(min=1), default=None,
              help="Processes to fit the take's segments on, this one included (1: only this one). Default: one per "
                   "CPU, no more than there are segments (two windows each) or than leave ~2 GiB of available memory "
                   "each; 1 on a GPU. The result does not depend on it.")
def fit(workspace: Path, take: str, fps: float, no_trackers: bool, no_suit_chain: bool, mounts_from: str | None, force: bool,
        no_collision: bool, relaxed_hands: bool, exact_contacts: bool, window: int, solver: str, take_step: str,
        device: str, threads: int, workers: int | None):  # fmt: skip
    """Fit both actors' anny bodies to a take, jointly.

    One shape per actor from the suit's segment lengths (and the registered height); per frame a
    closed-form retarget of the segment orientations, refined over windows of frames by L-BFGS on
    orientation, tracker, smoothness, floor and foot-stance terms plus an SDF collision term between
    the two bodies. The suit measures no fingers: where a hand lies on the partner, the collision
    term opens its thumb and fingers (between anny's relaxed hand and flat) before it moves any
    bone. The take is fitted in segments of two windows on --workers processes at once;
    consecutive segments are cross-faded over the frames they share (--solver take: the whole
    take as one problem instead, in one process). Writes bodies.npz,
    shapes.json, frames.npz and report.html / report.png. Runs `sync` and `fuse` first if needed.

    \b
    Examples:
      dualhuman fit WS --take T001
      dualhuman fit WS --take T002 --mounts-from CAL --workers 4
      dualhuman fit WS --take T003 --solver take --device cuda
    """
    from dualhuman_builder.fit.fitter import FitConfig
    from dualhuman_builder.fit.stage import run_fit
    from dualhuman_builder.workspace import Workspace

    cfg = FitConfig(collision=not no_collision, hand_opening=not relaxed_hands, collision_hold_contacts=not exact_contacts,
                    window=window, solver=solver, device=device, torch_threads=threads,
                    take_step=take_step)  # fmt: skip
    with Workspace.open(workspace) as ws:
        res = run_fit(ws, take, cfg, force=force, log=console.print, fps=fps, use_trackers=not no_trackers,
                      suit_chain=not no_suit_chain, workers=workers, mounts_from=mounts_from)  # fmt: skip
        console.print(f"fit {'up to date' if res.skipped else 'done'}; report: {res.artifacts.get('report.html')}", highlight=False)
        _made_stale(res)


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
@click.option("--force", is_flag=True,
              help="Run again even when the stage is up to date; the stages that read it become stale.")
def contacts(workspace: Path, take: str, threshold: float, band: float, workers: int | None, force: bool):
    """Per-vertex contacts between the two fitted bodies, frame by frame.

    For every frame, both ways, the signed distance of each body's vertices to the other body's
    surface within --band (libigl, pseudonormal sign; frames whose bodies are farther apart than
    the band are skipped). A vertex closer than --threshold, or inside the other body, is in
    contact. Writes contacts.npz (per-vertex labels, bit-packed; float16 distances; a per-frame
    flag) and contacts.json (region-level contact events: body-part pairs with start and end
    frames, like CHI3D's signatures; counts). Needs the take's fit stage.

    \b
    Examples:
      dualhuman contacts WS --take T001
      dualhuman contacts WS --take T001 --threshold 0.01 --force
    """
    from dualhuman_builder.contacts.stage import run_contacts
    from dualhuman_builder.workspace import Workspace

    with Workspace.open(workspace) as ws:
        res = run_contacts(ws, take, threshold_m=threshold, band_m=band, force=force, log=console.print, workers=workers)
        console.print(f"contacts {'up to date' if res.skipped else 'done'}: {res.artifacts.get('contacts.json')}", highlight=False)
        _made_stale(res)


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
@click.option("--force", is_flag=True, help="Render again even when the stage is up to date; the sheet becomes stale.")
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
        else:
            _made_stale(res)

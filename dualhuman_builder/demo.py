"""``dualhuman demo``: run every pipeline stage that exists so far on simulated actors.

What it does now (each step goes through the workspace, so a second run is a no-op):

1. creates (or reuses) the workspace and registers the simulated rig ``rigs/sim.toml``;
2. registers two actors of different statures and solves their anny shapes from stature;
3. registers take ``DEMO`` with sequence ``handshake`` and runs the ``scene`` stage: a generated
   ground-truth handshake of the two actors (:mod:`dualhuman_builder.sim.scenes`, seed 3); it
   writes the scene (``scene.npz``: sequence, per-vertex distances to the partner, phases), the
   :class:`~dualhuman_builder.tracks.InteractionSequence` alone, meshes of the first frame and
   of the handshake (PLY, and a coloured GLB to open in any glTF viewer), a Mitsuba still
   ``preview.png`` of the handshake and ``strip.png``, six moments side by side with the
   ground-truth contacts painted yellow;
4. runs the ``devices`` stage: both suits, twelve trackers and two IMUs simulated from the scene
   (:mod:`dualhuman_builder.sim.studio`), summarised in ``devices.json`` (samples per stream,
   rates, the realised clock offsets, drifts and tracker losses).

5. runs the ``capture`` stage: the same simulated devices played onto real loopback transports
   (both suits on one MVN UDP port, the trackers on another, the Xbus MTi on a pseudo-terminal with
   its configuration dialogue, the CAN MTi on python-can's virtual bus) and recorded by the live
   sources into ``take.mcap`` (:mod:`dualhuman_builder.capture`), checked, and replayed to verify
   that re-decoding gives the recorded samples bit for bit (``capture.json``).

6. records the session's calibration take ``CALIB`` the same way (its ``scene`` and ``capture``
   stages, sequence ``calibration``: the two actors, apart, bow, bend, twist, squat, raise their
   arms and turn on the spot, wearing the same simulated devices), and syncs it: its tracker
   mounts carry over to ``DEMO`` (``dualhuman sync --mounts-from``).

7. runs ``sync`` (mounts from ``CALIB``), ``fuse`` and ``fit`` on the handshake
   (:mod:`dualhuman_builder.fit.stages`): clocks and tracker mounts (``sync.json``), fused
   skeletons, both actors' anny bodies fitted jointly with the collision term (``bodies.npz``,
   ``shapes.json``) and ``report.html`` / ``report.png``.

8. runs ``contacts`` (per-vertex contacts between the fitted bodies, region events:
   ``contacts.npz``, ``contacts.json``), ``render`` (Mitsuba: four views around the pair, every 10th
   frame at 192 px: RGB, depth, masks, keypoints, cameras, under ``artifacts/DEMO/_take/render/``)
   and ``sheet`` (``contact_sheet.png``: views x frames with masks and keypoints overlaid and the
   contacts painted on the meshes);

9. exports the dataset to ``WS/export/`` and verifies it (``dualhuman export verify WS/export``);
   the calibration take has no fit and is left out.

The demo always runs the whole pipeline that exists.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

DEMO_TAKE = "DEMO"
DEMO_SEQUENCE = "handshake"
DEMO_SCENE = {"type": "handshake", "seed": 3, "fps": 30.0}
DEMO_ACTORS = (("sim-a", 1.68, "female"), ("sim-b", 1.82, "male"))
#: The session's calibration take: the same actors and simulated devices (seed), another motion.
CALIB_TAKE = "CALIB"
CALIB_SEQUENCE = "calibration"
CALIB_SCENE = {"type": "calibration", "seed": DEMO_SCENE["seed"], "fps": DEMO_SCENE["fps"]}
ACTOR_COLOURS = ((0.80, 0.35, 0.25), (0.25, 0.45, 0.80))
#: The demo's simulated devices play this many times faster than real time while recorded. Real
#: time: 2x is the most a 2-core machine records losslessly (benchmarks/bench_capture.py), and near
#: that limit the send threads fall behind by milliseconds, which the clock sync then has to absorb.
DEMO_CAPTURE_SPEED = 1.0
#: Annotator name of the labels a generated scene comes with.
SCENE_ANNOTATOR = "dualhuman-scene"
#: The demo's render: four views of every 10th frame, small and quick on a CPU.
DEMO_RENDER = {"views": 4, "size": 192, "spp": 8, "every": 10}


@dataclass
class DemoResult:
    workspace: Path
    outputs: dict[str, Path] = field(default_factory=dict)
    ran: list[str] = field(default_factory=list)
    up_to_date: list[str] = field(default_factory=list)
    seconds: float = 0.0


def greeting_sequence(model, shapes: list[dict], frames: int = 60, fps: float = 30.0, distance_m: float = 1.2):
    """Two bodies facing each other ``distance_m`` apart (along Z), feet on the floor, raising
    their arms from the rest A-pose to a T-pose with eased timing. Returns an InteractionSequence."""
    import torch

    from dualhuman_builder.body.joints import tpose
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    s = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, frames))  # ease in/out, 0 -> 1
    tracks = []
    for i, shape in enumerate(shapes):
        shape_t = model.shape_tensor(shape)
        with torch.no_grad():
            target = tpose(model, shape_t).cpu().numpy()  # (J, 3) rotation vectors from rest
            floor = -float(model.rest(shape_t).vertices[0, :, 1].min())  # lift the soles onto y = 0
        pose = s[:, None, None] * target[None]  # rotvec scaling from zero is exact slerp
        facing = np.array([0.0, np.pi * i, 0.0])  # actor 1 turned 180 degrees about +Y
        pose[:, 0] = facing
        z = (-0.5 if i == 0 else 0.5) * distance_m
        transl = np.tile([0.0, floor, z], (frames, 1))
        tracks.append(BodyTrack.from_model(model, pose, transl, shape_t.cpu().numpy(), fps, actor=DEMO_ACTORS[i][0]))
    return InteractionSequence(tuple(tracks), take=DEMO_TAKE, labels=("demo",),
                               text=("Two people face each other and spread their arms.",))  # fmt: skip


def run_demo(workspace: str | Path = "demo-workspace", log: Callable[[str], None] = print) -> DemoResult:
    """Run the demo pipeline into ``workspace`` (created if missing); returns what it wrote."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.body.shape import shape_for_stature
    from dualhuman_builder.paths import RIGS_DIR
    from dualhuman_builder.workspace import Workspace

    t0 = time.perf_counter()
    result = DemoResult(Path(workspace))
    with Workspace.init(workspace) as ws:
        log(f"workspace {ws.root}")
        ws.add_rig(RIGS_DIR / "sim.toml")
        model = get_body_model()
        shapes = []
        for name, height, gender in DEMO_ACTORS:
            known = {a.name: a for a in ws.actors()}.get(name)
            if known is None or known.shape is None:
                shape = shape_for_stature(model, height, gender)
                ws.add_actor(name, height, gender, shape=shape, shape_source="stature")
                log(f"actor {name}: {height:.2f} m {gender}, anny shape solved from stature")
            shapes.append(ws.actor(name).shape)
        for take, seq, scene_params in ((DEMO_TAKE, DEMO_SEQUENCE, DEMO_SCENE), (CALIB_TAKE, CALIB_SEQUENCE, CALIB_SCENE)):
            _simulated_take(ws, result, model, shapes, take, seq, scene_params, log)
        if not ws.annotations(DEMO_TAKE):  # scene-generated sequences come labelled with their type and text
            from dualhuman_builder.export.labels import Annotation, check_annotation, load_vocabulary
            from dualhuman_builder.tracks import InteractionSequence

            gt = InteractionSequence.load(ws.artifacts("scene", DEMO_TAKE, DEMO_SEQUENCE)["sequence.npz"])
            ann = Annotation(DEMO_TAKE, DEMO_SEQUENCE, SCENE_ANNOTATOR, tuple(gt.labels), tuple(gt.text))
            ws.annotate([check_annotation(ann, load_vocabulary(ws.root), ws.take(DEMO_TAKE).actors)])

        # sync -> fuse -> fit on the recorded take (take-level stages reading the capture artifact)
        from dualhuman_builder.fit.stages import run_fit

        take_file = ws.artifacts("capture", DEMO_TAKE, DEMO_SEQUENCE)["take.mcap"]
        res = run_fit(ws, DEMO_TAKE, log=log, fps=DEMO_SCENE["fps"], take_file=take_file,
                      depends_on=[("capture", DEMO_SEQUENCE)], mounts_from=CALIB_TAKE,
                      mounts_take_file=ws.artifacts("capture", CALIB_TAKE, CALIB_SEQUENCE)["take.mcap"],
                      mounts_depends_on=[("capture", CALIB_SEQUENCE)])  # fmt: skip
        for stage in ("sync", "fuse"):
            result.outputs.update(ws.artifacts(stage, DEMO_TAKE))
        _note(result, log, "fit", res)

        # contacts -> render (a small ring: the demo is about looking, not volume) -> contact sheet
        from dualhuman_builder.contacts.stage import run_contacts
        from dualhuman_builder.render.sheet import run_sheet
        from dualhuman_builder.render.stage import run_render

        _note(result, log, "contacts", run_contacts(ws, DEMO_TAKE, log=log))
        _note(result, log, "render", run_render(ws, DEMO_TAKE, log=log, **DEMO_RENDER))
        _note(result, log, "sheet", run_sheet(ws, DEMO_TAKE, log=log))

        # the dataset, verified
        from dualhuman_builder.export.collect import run_export
        from dualhuman_builder.export.verify import verify_export

        export_dir = ws.root / "export"
        before = (export_dir / "manifest.json").read_bytes() if (export_dir / "manifest.json").exists() else None
        run_export(ws, export_dir, log=log)
        problems = verify_export(export_dir)
        if problems:
            from dualhuman_builder.errors import DualhumanError

            raise DualhumanError(f"the demo's export does not verify: {problems[:5]}")
        changed = before != (export_dir / "manifest.json").read_bytes()
        (result.ran if changed else result.up_to_date).append("export")
        log(f"export: {export_dir} ({'written' if changed else 'up to date'}; verified)")
        result.outputs["export"] = export_dir
    result.seconds = time.perf_counter() - t0
    return result


def _simulated_take(ws, result: DemoResult, model, shapes, take: str, sequence: str, params: dict, log) -> None:
    """Register ``take`` with its one ``sequence`` and run its ``scene`` (a generated scene of type
    ``params["type"]`` with the demo actors' shapes; the interaction's also gets its previews),
    ``devices`` and ``capture`` stages (the simulated devices of seed ``params["seed"]``). Another
    take than ``DEMO`` is noted as ``"<stage> (<take>)"``, its outputs as ``"<take>/<name>"``."""
    from dualhuman_builder.sim.scenes import GENERATOR_VERSION, NATURAL_DURATION

    calibration = params["type"] == "calibration"
    tag, prefix = ("", "") if take == DEMO_TAKE else (f" ({take})", f"{take}/")
    if take not in ws.takes():
        ws.add_take(take, rig="sim", actors=[a[0] for a in DEMO_ACTORS], meta={"simulated": True, "calibration": calibration})
    if sequence not in [s.name for s in ws.sequences(take)]:
        frames = int(round(NATURAL_DURATION[params["type"]] * params["fps"]))
        ws.add_sequence(take, sequence, 0, frames, labels=(params["type"],))

    def scene(out):
        from dualhuman_builder.sim.scenes import SceneParams, make_scene

        log(f"generating a {params['type']} (seed {params['seed']})...")
        sc = make_scene(SceneParams(shapes=(shapes[0], shapes[1]), names=tuple(a[0] for a in DEMO_ACTORS), **params),
                        model=model, log=log)  # fmt: skip
        sc.save(out.path("scene.npz"))
        sc.sequence.save(out.path("sequence.npz"))
        if calibration:
            return {"quality": sc.stats}
        log(f"scene quality: penetration {1000 * sc.stats['max_penetration_m']:.1f} mm, contact on "
            f"{100 * sc.stats['contact_frames_share']:.0f} % of the contact phase; rendering previews...")  # fmt: skip
        return {**_write_scene_views(model, sc, out), "quality": sc.stats}

    res = ws.run_stage("scene", scene, take=take, sequence=sequence, params={"actors": DEMO_ACTORS, "shapes": shapes, **params},
                       version=str(GENERATOR_VERSION))  # fmt: skip
    _note(result, log, "scene" + tag, res, prefix)

    def devices(out):
        from dualhuman_builder.sim.scenes import Scene
        from dualhuman_builder.sim.studio import simulate_studio

        sc = Scene.load(ws.artifacts("scene", take, sequence)["scene.npz"])
        summary = studio_summary(simulate_studio(sc.sequence, seed=params["seed"], progress=log))
        with open(out.path("devices.json"), "w") as f:
            json.dump(summary, f, indent=2)
        return {"samples": sum(summary["samples"].values())}

    res = ws.run_stage("devices", devices, take=take, sequence=sequence, params={"seed": params["seed"]},
                       depends_on=[("scene", sequence)])  # fmt: skip
    _note(result, log, "devices" + tag, res, prefix)

    def capture(out):
        summary = record_demo_take(ws.artifacts("scene", take, sequence)["scene.npz"], out.path("take.mcap"), log=log,
                                   take=take, devices_seed=params["seed"])  # fmt: skip
        with open(out.path("capture.json"), "w") as f:
            json.dump(summary, f, indent=2)
        return {k: summary[k] for k in ("samples", "lost", "replay_identical")}

    res = ws.run_stage("capture", capture, take=take, sequence=sequence, params={"seed": params["seed"], "speed": DEMO_CAPTURE_SPEED},
                       depends_on=[("scene", sequence)])  # fmt: skip
    _note(result, log, "capture" + tag, res, prefix)


def _note(result: DemoResult, log, stage: str, res, prefix: str = "") -> None:
    """Count a stage as run or up to date, and keep its artifacts (names prefixed by ``prefix``)."""
    (result.up_to_date if res.skipped else result.ran).append(stage)
    log(f"stage {stage}: {'up to date' if res.skipped else 'done'}")
    result.outputs.update({prefix + k: v for k, v in res.artifacts.items()})


def studio_summary(studio) -> dict:
    """What a person wants to know about a simulated take: samples per stream, rates, and the
    errors the simulators realised (clock offsets, suit drift, tracker losses)."""
    suits = {f"suit/{s.character}": {"rate_hz": s.rate_hz, "heading_drift_deg_per_min": round(float(np.degrees(s.heading_drift_rate_rad_s) * 60), 3),
                                     "root_drift_at_end_m": np.round(s.root_drift[-1], 4).tolist()}
             for s in studio.suits}  # fmt: skip
    trackers = {}
    for tr in studio.trackers:
        for i, serial in enumerate(tr.serials):
            trackers[f"vive/{serial}"] = {"segment": tr.segments[i], "rate_hz": tr.rate_hz,
                                          "losses": int((tr.loss_tracker == i).sum()),
                                          "invalid_samples": int((~tr.valid[i]).sum())}  # fmt: skip
    clocks = {name: {"offset_s": c.offset_s, "drift_ppm": c.drift_ppm}
              for name, c in [("suits", studio.suits[0].clock), ("trackers", studio.trackers[0].clock),
                              *((f"imu/{k}", v.clock) for k, v in studio.imus.items())]}  # fmt: skip
    return {"samples": studio.counts(), "suits": suits, "trackers": trackers, "clocks": clocks,
            "imus": {k: {"segment": v.segment, "rate_hz": v.rate_hz} for k, v in studio.imus.items()}}  # fmt: skip


def record_demo_take(scene_path: Path, take_path: Path, log: Callable[[str], None] = print, take: str = DEMO_TAKE,
                     devices_seed: int = DEMO_SCENE["seed"]) -> dict:  # fmt: skip
    """Record the scene's simulated studio through real loopback transports into ``take_path``
    (:func:`dualhuman_builder.capture.session.capture_take`), check the file, and check that
    re-decoding its raw packets gives the recorded samples bit for bit. Returns a summary."""
    from dualhuman_builder.capture.log.reader import check_take
    from dualhuman_builder.capture.replay import verify_replay
    from dualhuman_builder.capture.session import capture_take, plan_capture

    url = f"sim://{Path(scene_path).resolve()}?devices={devices_seed}"
    log(f"recording the simulated studio on loopback ({DEMO_CAPTURE_SPEED:g}x real time)...")
    res = capture_take(plan_capture(sources=[url]), take_path, take=take, sim_speed=DEMO_CAPTURE_SPEED, progress=log)
    if res.error:
        from dualhuman_builder.errors import DualhumanError

        raise DualhumanError(f"the demo capture failed: {res.error}")
    check = check_take(take_path)
    replay = verify_replay(take_path)
    lost = {name: int(sum(st.get(k, 0) for k in ("lost", "kernel_drops", "incomplete")))
            for name, st in res.source_stats.items()}  # fmt: skip
    log(f"take: {sum(res.samples_per_topic.values())} samples, {check.messages} messages, lost {lost}, "
        f"replay {'bit-identical' if replay.identical else 'DIFFERS'}")  # fmt: skip
    return {"samples": sum(res.samples_per_topic.values()), "per_topic": dict(res.samples_per_topic), "lost": lost,
            "sources": res.source_stats, "events": res.events, "messages": check.messages, "complete": check.ok,
            "replay_identical": replay.identical, "seconds": round(res.duration_s, 2)}  # fmt: skip


def _write_scene_views(model, sc, out) -> dict:
    """PLY meshes of the first frame and of the middle of the contact, a coloured GLB of the
    latter, the still ``preview.png`` and the contact strip ``strip.png``."""
    import trimesh

    from dualhuman_builder.render.preview import render_preview, render_strip

    seq = sc.sequence
    faces = model.faces.cpu().numpy()
    a, b = sc.contact_phases[0]
    touch = min(int(round(0.5 * (a + b) * seq.fps)), seq.num_frames - 1)
    shown = []
    for track, colour in zip(seq.actors, ACTOR_COLOURS):
        verts = track.vertices()
        for tag, frame in (("first", 0), ("contact", touch)):
            mesh = trimesh.Trimesh(verts[frame], faces, process=False)
            mesh.export(out.path(f"meshes/{track.actor}_{tag}.ply"))
        rgba = np.array([*[int(255 * c) for c in colour], 255], dtype=np.uint8)
        shown.append(trimesh.Trimesh(verts[touch], faces, vertex_colors=np.tile(rgba, (len(verts[touch]), 1)), process=False))
    trimesh.Scene(shown).export(out.path("preview.glb"))
    info = render_preview([(m.vertices, faces, c) for m, c in zip(shown, ACTOR_COLOURS)], out.path("preview.png"))
    strip = render_strip(seq, faces, out.path("strip.png"), frames=6, colours=ACTOR_COLOURS, highlight=sc.contact_labels())
    return {"preview_variant": info["variant"], "preview_seconds": round(info["seconds"], 3),
            "strip_seconds": round(strip["seconds"], 3), "contact_frame": touch}  # fmt: skip

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

6. runs ``sync``, ``fuse`` and ``fit`` on that take (:mod:`dualhuman_builder.fit.stages`): clocks
   and tracker mounts (``sync.json``), fused skeletons, both actors' anny bodies fitted jointly
   with the collision term (``bodies.npz``, ``shapes.json``) and ``report.html`` / ``report.png``.

7. runs ``contacts`` (per-vertex contacts between the fitted bodies, region events:
   ``contacts.npz``, ``contacts.json``), ``render`` (Mitsuba: four views around the pair, every 10th
   frame at 192 px: RGB, depth, masks, keypoints, cameras, under ``artifacts/DEMO/_take/render/``)
   and ``sheet`` (``contact_sheet.png``: views x frames with masks and keypoints overlaid and the
   contacts painted on the meshes);

8. exports the dataset to ``WS/export/`` and verifies it (``dualhuman export verify WS/export``).

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
        if DEMO_TAKE not in ws.takes():
            ws.add_take(DEMO_TAKE, rig="sim", actors=[a[0] for a in DEMO_ACTORS], meta={"simulated": True})
        if DEMO_SEQUENCE not in [s.name for s in ws.sequences(DEMO_TAKE)]:
            from dualhuman_builder.sim.scenes import NATURAL_DURATION

            frames = int(round(NATURAL_DURATION[DEMO_SCENE["type"]] * DEMO_SCENE["fps"]))
            ws.add_sequence(DEMO_TAKE, DEMO_SEQUENCE, 0, frames, labels=(DEMO_SCENE["type"],))

        def scene(out):
            from dualhuman_builder.sim.scenes import SceneParams, make_scene

            log(f"generating a {DEMO_SCENE['type']} (seed {DEMO_SCENE['seed']})...")
            sc = make_scene(SceneParams(shapes=(shapes[0], shapes[1]), names=tuple(a[0] for a in DEMO_ACTORS), **DEMO_SCENE),
                            model=model, log=log)  # fmt: skip
            sc.save(out.path("scene.npz"))
            sc.sequence.save(out.path("sequence.npz"))
            log(f"scene quality: penetration {1000 * sc.stats['max_penetration_m']:.1f} mm, contact on "
                f"{100 * sc.stats['contact_frames_share']:.0f} % of the contact phase; rendering previews...")  # fmt: skip
            return {**_write_scene_views(model, sc, out), "quality": sc.stats}

        from dualhuman_builder.sim.scenes import GENERATOR_VERSION

        params = {"actors": DEMO_ACTORS, "shapes": shapes, **DEMO_SCENE}
        res = ws.run_stage("scene", scene, take=DEMO_TAKE, sequence=DEMO_SEQUENCE, params=params,
                           version=str(GENERATOR_VERSION))  # fmt: skip
        _note(result, log, "scene", res)
        if not ws.annotations(DEMO_TAKE):  # scene-generated sequences come labelled with their type and text
            from dualhuman_builder.export.labels import Annotation, check_annotation, load_vocabulary
            from dualhuman_builder.tracks import InteractionSequence

            gt = InteractionSequence.load(ws.artifacts("scene", DEMO_TAKE, DEMO_SEQUENCE)["sequence.npz"])
            ann = Annotation(DEMO_TAKE, DEMO_SEQUENCE, SCENE_ANNOTATOR, tuple(gt.labels), tuple(gt.text))
            ws.annotate([check_annotation(ann, load_vocabulary(ws.root), ws.take(DEMO_TAKE).actors)])

        def devices(out):
            from dualhuman_builder.sim.scenes import Scene
            from dualhuman_builder.sim.studio import simulate_studio

            sc = Scene.load(ws.artifacts("scene", DEMO_TAKE, DEMO_SEQUENCE)["scene.npz"])
            studio = simulate_studio(sc.sequence, seed=DEMO_SCENE["seed"], progress=log)
            summary = studio_summary(studio)
            with open(out.path("devices.json"), "w") as f:
                json.dump(summary, f, indent=2)
            return {"samples": sum(summary["samples"].values())}

        res = ws.run_stage("devices", devices, take=DEMO_TAKE, sequence=DEMO_SEQUENCE, params={"seed": DEMO_SCENE["seed"]},
                           depends_on=[("scene", DEMO_SEQUENCE)])  # fmt: skip
        _note(result, log, "devices", res)

        def capture(out):
            scene_path = ws.artifacts("scene", DEMO_TAKE, DEMO_SEQUENCE)["scene.npz"]
            summary = record_demo_take(scene_path, out.path("take.mcap"), log=log)
            with open(out.path("capture.json"), "w") as f:
                json.dump(summary, f, indent=2)
            return {k: summary[k] for k in ("samples", "lost", "replay_identical")}

        res = ws.run_stage("capture", capture, take=DEMO_TAKE, sequence=DEMO_SEQUENCE,
                           params={"seed": DEMO_SCENE["seed"], "speed": DEMO_CAPTURE_SPEED},
                           depends_on=[("scene", DEMO_SEQUENCE)])  # fmt: skip
        _note(result, log, "capture", res)

        # sync -> fuse -> fit on the recorded take (take-level stages reading the capture artifact)
        from dualhuman_builder.fit.stages import run_fit

        take_file = ws.artifacts("capture", DEMO_TAKE, DEMO_SEQUENCE)["take.mcap"]
        res = run_fit(ws, DEMO_TAKE, log=log, fps=DEMO_SCENE["fps"], take_file=take_file,
                      depends_on=[("capture", DEMO_SEQUENCE)])  # fmt: skip
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


def _note(result: DemoResult, log, stage: str, res) -> None:
    (result.up_to_date if res.skipped else result.ran).append(stage)
    log(f"stage {stage}: {'up to date' if res.skipped else 'done'}")
    result.outputs.update(res.artifacts)


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


def record_demo_take(scene_path: Path, take_path: Path, log: Callable[[str], None] = print) -> dict:
    """Record the scene's simulated studio through real loopback transports into ``take_path``
    (:func:`dualhuman_builder.capture.session.capture_take`), check the file, and check that
    re-decoding its raw packets gives the recorded samples bit for bit. Returns a summary."""
    from dualhuman_builder.capture.log.reader import check_take
    from dualhuman_builder.capture.replay import verify_replay
    from dualhuman_builder.capture.session import capture_take, plan_capture

    url = f"sim://{Path(scene_path).resolve()}?devices={DEMO_SCENE['seed']}"
    log(f"recording the simulated studio on loopback ({DEMO_CAPTURE_SPEED:g}x real time)...")
    res = capture_take(plan_capture(sources=[url]), take_path, take=DEMO_TAKE, sim_speed=DEMO_CAPTURE_SPEED, progress=log)
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

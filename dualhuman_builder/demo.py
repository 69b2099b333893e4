"""``dualhuman demo``: run every pipeline stage that exists so far on simulated actors.

What it does now (each step goes through the workspace, so a second run is a no-op):

1. creates (or reuses) the workspace and registers the simulated rig ``rigs/sim.toml``;
2. registers two actors of different statures and solves their anny shapes from stature;
3. registers take ``DEMO`` with sequence ``greeting`` and runs the ``scene`` stage: both bodies
   stand 1.2 m apart facing each other and raise their arms from anny's rest A-pose to a T-pose;
   it writes the :class:`~dualhuman_builder.tracks.InteractionSequence`, meshes of the first and
   last frames (PLY, and a coloured GLB to open in any glTF viewer) and a Mitsuba render
   ``preview.png``.

Later stages (simulated devices, capture, sync, fit, contacts, render, export) join here as they
land; the demo always runs the whole pipeline that exists.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

DEMO_TAKE = "DEMO"
DEMO_SEQUENCE = "greeting"
DEMO_ACTORS = (("sim-a", 1.68, "female"), ("sim-b", 1.82, "male"))
ACTOR_COLOURS = ((0.80, 0.35, 0.25), (0.25, 0.45, 0.80))


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
            ws.add_sequence(DEMO_TAKE, DEMO_SEQUENCE, 0, 60, labels=("demo",))

        def scene(out):
            seq = greeting_sequence(model, shapes)
            seq.save(out.path("sequence.npz"))
            return _write_scene_views(model, seq, out)

        res = ws.run_stage("scene", scene, take=DEMO_TAKE, sequence=DEMO_SEQUENCE,
                           params={"actors": DEMO_ACTORS, "shapes": shapes, "frames": 60, "fps": 30.0})  # fmt: skip
        (result.up_to_date if res.skipped else result.ran).append("scene")
        log(f"stage scene: {'up to date' if res.skipped else 'done'}")
        result.outputs.update(res.artifacts)
    result.seconds = time.perf_counter() - t0
    return result


def _write_scene_views(model, seq, out) -> dict:
    """PLY meshes of the first and last frames, a coloured GLB of the last, and preview.png."""
    import trimesh

    from dualhuman_builder.render.preview import render_preview

    faces = model.faces.cpu().numpy()
    last = []
    for track, colour in zip(seq.actors, ACTOR_COLOURS):
        verts = track.vertices()
        for tag, frame in (("first", 0), ("last", seq.num_frames - 1)):
            mesh = trimesh.Trimesh(verts[frame], faces, process=False)
            mesh.export(out.path(f"meshes/{track.actor}_{tag}.ply"))
        rgba = np.array([*[int(255 * c) for c in colour], 255], dtype=np.uint8)
        last.append(trimesh.Trimesh(verts[-1], faces, vertex_colors=np.tile(rgba, (len(verts[-1]), 1)), process=False))
    trimesh.Scene(last).export(out.path("preview.glb"))
    info = render_preview([(m.vertices, faces, c) for m, c in zip(last, ACTOR_COLOURS)], out.path("preview.png"))
    return {"preview_variant": info["variant"], "preview_seconds": round(info["seconds"], 3)}

"""The ``scene`` and ``devices`` workspace stages of a simulated take, and :func:`simulate_take`,
which runs them and the ``capture`` stage for one take (idempotent, crash-safe: see
:mod:`dualhuman_builder.workspace.runner`).

Artifacts (under ``WS/artifacts/TAKE/SEQUENCE/<stage>/``):

* ``scene``: ``scene.npz`` (:class:`~dualhuman_builder.sim.scenes.Scene`: sequence, per-vertex
  signed distances to the partner, stance, phases), ``sequence.npz`` (the
  :class:`~dualhuman_builder.tracks.InteractionSequence` alone) and, for an interaction (not a
  calibration take), previews: ``meshes/<actor>_{first,contact}.ply``, ``preview.glb`` (both
  bodies at the contact, coloured), ``preview.png`` (a Mitsuba still) and ``strip.png`` (six
  moments, ground-truth contact vertices painted yellow);
* ``devices``: ``devices.json`` (samples per stream, rates, and the errors the simulators realised:
  clock offsets and drifts, suit drift, tracker losses; the device error ``preset`` and ``drawn``,
  every parameter the preset drew for the take, :func:`~dualhuman_builder.sim.presets.draw_device_errors`:
  for evaluation only, never read by sync or fit).

The ``capture`` stage then records the scene's simulated studio through real loopback transports
(``sim://SCENE.npz?devices=SEED``, :mod:`dualhuman_builder.capture.stage`).
"""

from __future__ import annotations

import json
from typing import Callable, Sequence

import numpy as np

from dualhuman_builder.workspace.runner import Stage

SCENE_FILE, SEQUENCE_FILE, DEVICES_FILE = "scene.npz", "sequence.npz", "devices.json"
SCENE = Stage("scene", per="sequence",
              artifacts=(SCENE_FILE, SEQUENCE_FILE, "preview.png", "strip.png", "preview.glb", "meshes/{actor}_first.ply",
                         "meshes/{actor}_contact.ply"),
              command="dualhuman sim take {ws} --take {take}")  # fmt: skip
DEVICES = Stage("devices", per="sequence", artifacts=(DEVICES_FILE,), reads=("scene",),
                command="dualhuman sim take {ws} --take {take}")  # fmt: skip
#: The two simulated actors a take gets when none are named: ``(name, stature m, gender)``.
DEFAULT_ACTORS = (("sim-a", 1.68, "female"), ("sim-b", 1.82, "male"))
#: Colours of the two actors in the previews (linear RGB).
ACTOR_COLOURS = ((0.80, 0.35, 0.25), (0.25, 0.45, 0.80))
#: Annotator name of the labels a generated scene comes with.
SCENE_ANNOTATOR = "dualhuman-scene"


def ensure_actors(ws, actors: Sequence[tuple[str, float, str]], model=None,
                  log: Callable[[str], None] = print) -> list[dict]:  # fmt: skip
    """Register each ``(name, stature m, gender)`` actor the workspace lacks (or knows without a
    shape) with an anny shape solved from its stature; returns the actors' shapes in order."""
    from dualhuman_builder.body.shape import shape_for_stature

    shapes = []
    for name, height, gender in actors:
        known = {a.name: a for a in ws.actors()}.get(name)
        if known is None or known.shape is None:
            if model is None:
                from dualhuman_builder.body.model import get_body_model

                model = get_body_model()
            ws.add_actor(name, height, gender, shape=shape_for_stature(model, height, gender), shape_source="stature")
            log(f"actor {name}: {height:.2f} m {gender}, anny shape solved from stature")
        shapes.append(ws.actor(name).shape)
    return shapes


def run_scene(ws, take: str, sequence: str, params: dict, actors: Sequence[tuple[str, float, str]], shapes: Sequence[dict],
              model=None, force: bool = False, log: Callable[[str], None] = print):  # fmt: skip
    """The ``scene`` stage: a generated scene (:func:`~dualhuman_builder.sim.scenes.make_scene`)
    with ``params`` (``type``, ``seed``, ``fps``, and any other
    :class:`~dualhuman_builder.sim.scenes.SceneParams` field) of the two ``actors`` (``(name,
    stature m, gender)``) with anny ``shapes``. Returns the StageResult."""
    from dualhuman_builder.sim.scenes import GENERATOR_VERSION

    calibration = params["type"] == "calibration"

    def compute(out):
        from dualhuman_builder.body.model import get_body_model
        from dualhuman_builder.sim.generate import generate_scene
        from dualhuman_builder.sim.scenes import SceneParams

        body = model or get_body_model()
        log(f"generating a {params['type']} (seed {params['seed']})...")
        sc = generate_scene(SceneParams(shapes=(shapes[0], shapes[1]), names=tuple(a[0] for a in actors), **params),
                        model=body, log=log)  # fmt: skip
        sc.save(out.path(SCENE_FILE))
        sc.sequence.save(out.path(SEQUENCE_FILE))
        if calibration:
            return {"quality": sc.stats}
        log(f"scene quality: penetration {1000 * sc.stats['max_penetration_m']:.1f} mm, contact on "
            f"{100 * sc.stats['contact_frames_share']:.0f} % of the contact phase; rendering previews...")  # fmt: skip
        return {**write_scene_views(body, sc, out), "quality": sc.stats}

    return ws.run_stage(SCENE, compute, take=take, sequence=sequence,
                        params={"actors": tuple(actors), "shapes": list(shapes), **params},
                        version=str(GENERATOR_VERSION), force=force)  # fmt: skip


def run_devices(ws, take: str, sequence: str, seed: int, force: bool = False, log: Callable[[str], None] = print,
                preset: str = "ideal"):  # fmt: skip
    """The ``devices`` stage: the simulated studio of the sequence's scene with device seed
    ``seed`` and device error ``preset`` (:func:`~dualhuman_builder.sim.studio.simulate_studio`),
    summarised. Returns the StageResult."""
    from dualhuman_builder.sim.presets import check_preset

    check_preset(preset)

    def compute(out):
        from dualhuman_builder.sim.studio import simulate_studio

        sc = load_scene(ws, take, sequence)
        contacts = None if preset == "ideal" else sc.distances
        studio = simulate_studio(sc.sequence, seed=seed, progress=log, preset=preset, contacts=contacts)
        summary = studio_summary(studio)
        with open(out.path(DEVICES_FILE), "w") as f:
            json.dump(summary, f, indent=2)
        return {"samples": sum(summary["samples"].values()), "preset": preset}

    return ws.run_stage(DEVICES, compute, take=take, sequence=sequence, params=_device_params(seed, preset),
                        depends_on=[("scene", sequence)], force=force)  # fmt: skip


def _device_params(seed: int, preset: str, **more) -> dict:
    """Stage parameters of a take's devices: the ``ideal`` preset leaves them as they were without
    one, so takes made before presets existed stay up to date."""
    return {"seed": seed, **more} if preset == "ideal" else {"seed": seed, "preset": preset, **more}


def device_url(scene_path, seed: int, preset: str = "ideal") -> str:
    """The ``sim://`` URL that plays the scene file ``scene_path`` with device seed ``seed`` and
    ``preset``."""
    from pathlib import Path

    url = f"sim://{Path(scene_path).resolve()}?devices={seed}"
    return url if preset == "ideal" else f"{url}&preset={preset}"


def load_scene(ws, take: str, sequence: str):
    """The sequence's ground-truth :class:`~dualhuman_builder.sim.scenes.Scene` (its scene stage
    must be done)."""
    from dualhuman_builder.sim.scenes import Scene

    return Scene.load(SCENE.artifact(ws, take, SCENE_FILE, sequence, what="ground-truth scene"))


def simulate_take(ws, take: str, sequence: str, params: dict, actors: Sequence[tuple[str, float, str]],
                  shapes: Sequence[dict], *, speed: float = 1.0, model=None, force: bool = False,
                  log: Callable[[str], None] = print, preset: str = "ideal", device_seed: int | None = None) -> dict:  # fmt: skip
    """Register ``take`` (rig ``sim``, the ``actors``) with its one ``sequence`` if new, then run
    its ``scene``, ``devices`` and ``capture`` stages: a generated scene, its simulated devices
    (device seed ``device_seed``, by default the scene's ``params["seed"]``; takes of one studio day
    share theirs, and so their tracker mounts; device error ``preset``), and their recording through real
    loopback transports at ``speed`` times real time. The take's ``sync``, ``fuse`` and ``fit``
    stages then read that recording. Returns ``{stage: StageResult}``."""
    from dualhuman_builder.capture.stage import run_capture
    from dualhuman_builder.sim.presets import check_preset
    from dualhuman_builder.sim.scenes import NATURAL_DURATION, SESSION_TYPE
    from dualhuman_builder.sim.session import DEFAULT_DURATION_S

    check_preset(preset)
    calibration = params["type"] == "calibration"
    if take not in ws.takes():
        ws.add_take(take, rig="sim", actors=[a[0] for a in actors], meta={"simulated": True, "calibration": calibration})
    if sequence not in [s.name for s in ws.sequences(take)]:
        if params["type"] == SESSION_TYPE:  # many meetings: each one's type is in the scene's phases
            seconds, labels = params.get("duration") or DEFAULT_DURATION_S, ()
        else:
            seconds, labels = params.get("duration") or NATURAL_DURATION[params["type"]], (params["type"],)
        ws.add_sequence(take, sequence, 0, int(round(seconds * params["fps"])), labels=labels)
    results = {"scene": run_scene(ws, take, sequence, params, actors, shapes, model=model, force=force, log=log)}
    seed = int(params["seed"] if device_seed is None else device_seed)
    results["devices"] = run_devices(ws, take, sequence, seed, force=force, log=log, preset=preset)
    scene_path = SCENE.artifact(ws, take, SCENE_FILE, sequence)
    url = device_url(scene_path, seed, preset)
    results["capture"] = run_capture(ws, take, sequence, url, speed=speed,
                                     params=_device_params(seed, preset, speed=speed),
                                     depends_on=[("scene", sequence)], force=force, log=log)  # fmt: skip
    return results


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
    out = {"samples": studio.counts(), "suits": suits, "trackers": trackers, "clocks": clocks,
           "imus": {k: {"segment": v.segment, "rate_hz": v.rate_hz} for k, v in studio.imus.items()}}  # fmt: skip
    if studio.devices is not None:
        for s in studio.suits:
            lost_s = float(np.sum(s.dropout_stop_ns - s.dropout_start_ns)) * 1e-9
            suits[f"suit/{s.character}"].update({"dropouts": int(len(s.dropout_start_ns)), "dropout_s": round(lost_s, 3)})
        out["preset"] = studio.devices.preset
        out["drawn"] = studio.devices.drawn
    return out


def write_scene_views(model, sc, out) -> dict:
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

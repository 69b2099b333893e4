"""Accuracy of the whole path on simulated takes, against the scene's ground truth.

:func:`record_simulated_take` generates a scene, plays its simulated devices onto real loopback
transports and records the take (the same path as ``dualhuman capture --source sim://...``);
:func:`evaluate_take_fit` compares a :class:`~dualhuman_builder.fit.process.TakeFit` with the
scene and the simulators' realised errors:

* ``mpjpe_mm``: mean 22-joint position error; ``root_mm``: mean pelvis-centre (root) error;
* ``max_penetration_mm`` / ``penetrating_share``: between the two fitted bodies, worst frame;
* ``clock_offset_error_ms`` / ``clock_drift_error_ppm``: the tracker clock against the suits';
* ``mount_rotation_error_deg``: each tracker's mounting rotation against the one that is
  identifiable from the data (the simulated mount seen from the suit's reported segment frame,
  which carries the suit's own sensor-to-segment misalignment); ``mount_rotation_error_raw_deg``
  against the simulated mount itself; ``mount_translation_error_mm`` (mean over trackers) and
  ``mount_translation_error_max_mm``: each tracker's mounting offset against the simulated one
  seen from the suit's reported segment frame (where sync solves it);
* ``foot_slide_mm``: mean horizontal step per frame of the fitted soles in ground-truth stance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.evaluation.contacts import gt_frames


def record_simulated_take(scene_type: str, seed: int, out_dir: str | Path, fps: float = 30.0,
                          speed: float = 1.0, duration: float | None = None, model=None,
                          preset: str = "ideal") -> tuple[Path, object]:  # fmt: skip
    """Generate a ``scene_type`` scene (seed, fps), record its studio (device seed ``seed``, device
    error ``preset``: :data:`~dualhuman_builder.sim.presets.PRESETS`) through loopback transports at
    ``speed`` times real time. Returns ``(take_path, scene)``; a take of a preset other than
    ``ideal`` is named with it (``hug-3-realistic.mcap``), and the parameters the preset drew are
    written next to it (``hug-3-realistic.devices.json``, for evaluation). Keep ``speed`` at 1
    when the sync is scored: above the highest lossless multiple of the machine
    (``benchmarks/bench_capture.py``) the host receive times lag the devices' own timing, and the
    score would measure that lag, not the sync."""
    import json

    from dualhuman_builder.capture.recording import capture_take, plan_capture
    from dualhuman_builder.sim.presets import check_preset, draw_device_errors
    from dualhuman_builder.sim.generate import generate_scene
    from dualhuman_builder.sim.scenes import SceneParams
    from dualhuman_builder.sim.stage import device_url

    check_preset(preset)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    scene = generate_scene(SceneParams(type=scene_type, seed=seed, fps=fps, duration=duration), model=model)
    scene_path = scene.save(out / f"{scene_type}-{seed}.scene.npz")
    name = f"{scene_type}-{seed}" if preset == "ideal" else f"{scene_type}-{seed}-{preset}"
    take = out / f"{name}.mcap"
    res = capture_take(plan_capture(sources=[device_url(scene_path, seed, preset)]), take,
                       take=name.replace("_", "-"), sim_speed=speed)  # fmt: skip
    if preset != "ideal":
        (out / f"{name}.devices.json").write_text(json.dumps(draw_device_errors(preset, seed).drawn, indent=2))
    if res.error:
        raise RuntimeError(f"recording the simulated take failed: {res.error}")
    return take, scene


def procrustes_aligned(pred: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """``pred (T, J, 3)`` aligned to ``truth`` per frame by the similarity transform (rotation, uniform
    scale, translation) that minimises the squared joint distances (Umeyama's closed form): what
    PA-MPJPE measures after, the pose's error without its global placement and size."""
    p = pred - pred.mean(1, keepdims=True)
    q = truth - truth.mean(1, keepdims=True)
    u, sv, vt = np.linalg.svd(np.einsum("tji,tjk->tik", p, q))
    d = np.sign(np.linalg.det(u @ vt))
    sv[:, -1] *= d
    u[:, :, -1] *= d[:, None]
    rot = u @ vt  # (T, 3, 3): p @ rot ~ q
    scale = sv.sum(1) / np.maximum((p**2).sum((1, 2)), 1e-12)
    return scale[:, None, None] * (p @ rot) + truth.mean(1, keepdims=True)


def evaluate_take_fit(tf, scene, seed: int, model=None, contacts: bool = True, preset: str = "ideal") -> dict:
    """Errors of ``tf`` (a TakeFit) against ``scene`` recorded with devices seed ``seed`` and device
    error preset ``preset`` (:mod:`~dualhuman_builder.sim.presets`; the clocks' and mounts' truth is
    drawn again from them): ``mpjpe_mm``, ``pa_mpjpe_mm`` (after :func:`procrustes_aligned`), ``root_mm``,
    ``foot_slide_mm``, penetration, clock and mount errors. With
    ``contacts`` (two actors), the fitted pair's contacts against the scene's at the contact threshold
    (:func:`~dualhuman_builder.evaluation.contacts.take_fit_contacts`): ``contact_precision``,
    ``contact_recall``, ``contact_f1`` (per vertex, both actors, every frame), ``contact_regions``
    (region -> the same), ``contact_onset_error_ms`` / ``contact_offset_error_ms`` (mean over the
    region-pair events matched, ``contact_events_missed`` / ``contact_events_spurious`` the others)
    and ``contact_any_onset_error_ms`` / ``contact_any_offset_error_ms`` (runs of frames with any contact)."""
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.fit.fitter import FitConfig, stance_mask
    from dualhuman_builder.fit.skeleton import sole_vertices
    from dualhuman_builder.sim.studio import simulate_studio

    model = model or get_body_model()
    gt = scene.sequence
    fit = tf.fit.sequence
    actors = fit.actors if hasattr(fit, "actors") else fit
    idx = gt_frames(tf.sync.times_s, gt.fps, gt.num_frames)
    out: dict = {"frames": int(len(idx))}
    errs, pa_errs, roots, slides = [], [], [], []
    soles = sole_vertices(model)
    for k, track in enumerate(actors):
        g = gt.actors[k]
        jf, jg = track.joints(), g.joints()[idx]
        errs.append(np.linalg.norm(jf - jg, axis=-1))
        pa_errs.append(np.linalg.norm(procrustes_aligned(jf, jg) - jg, axis=-1))
        roots.append(np.linalg.norm(np.asarray(track.transl) - np.asarray(g.transl)[idx], axis=-1))
        vf, vg = track.vertices(), g.vertices()[idx]
        for side in ("L", "R"):
            ids = soles[side]
            pf, pg = vf[:, ids].mean(1), vg[:, ids].mean(1)
            sole_off = np.array([pg[:, 1].min() - vg[:, ids, 1].min()])  # sole point above the lowest sole vertex
            st = stance_mask(pg[:, None], gt.fps, sole_off, FitConfig())[:, 0]
            both = st[1:] & st[:-1]
            step = np.linalg.norm((pf[1:] - pf[:-1])[:, [0, 2]], axis=-1)
            if both.any():
                slides.append(step[both])
    out["mpjpe_mm"] = float(np.mean(np.concatenate(errs)) * 1000)
    out["pa_mpjpe_mm"] = float(np.mean(np.concatenate(pa_errs)) * 1000)
    out["root_mm"] = float(np.mean(np.concatenate(roots)) * 1000)
    out["foot_slide_mm"] = float(np.mean(np.concatenate(slides)) * 1000) if slides else 0.0
    s = tf.fit.summary
    out["max_penetration_mm"] = s.get("max_penetration_after_mm", float("nan"))
    out["penetrating_share"] = s.get("penetrating_share_after", float("nan"))
    out["max_penetration_before_mm"] = s.get("max_penetration_before_mm", float("nan"))
    out["penetrating_share_before"] = s.get("penetrating_share_before", float("nan"))
    if contacts and len(actors) == 2:
        from dualhuman_builder.evaluation.contacts import take_fit_contacts

        c = take_fit_contacts(tf, scene)
        out.update({"contact_precision": c["precision"], "contact_recall": c["recall"], "contact_f1": c["f1"],
                    "contact_regions": c["regions"], "contact_onset_error_ms": c["events"]["onset_ms"],
                    "contact_offset_error_ms": c["events"]["offset_ms"], "contact_events_missed": c["events"]["missed"],
                    "contact_events_spurious": c["events"]["spurious"],
                    "contact_any_onset_error_ms": c["any_events"]["onset_ms"],
                    "contact_any_offset_error_ms": c["any_events"]["offset_ms"]})  # fmt: skip
    # clocks and mounts against the simulators' truth (deterministic for the seed)
    studio = simulate_studio(gt, seed=seed, preset=preset)
    clocks = tf.sync.report.get("clocks", {})
    trk = [v for k, v in clocks.items() if k.startswith("source:")]
    if trk:
        truth = studio.trackers[0].clock
        out["clock_offset_error_ms"] = abs(trk[0]["offset_s"] - truth.offset_s) * 1000
        out["clock_drift_error_ppm"] = abs(trk[0]["drift_ppm"] - truth.drift_ppm)
    errs = mount_errors(tf.sync, studio)
    if len(errs["rotation_deg"]):
        out["mount_rotation_error_deg"] = float(np.max(errs["rotation_deg"]))
        out["mount_rotation_error_raw_deg"] = float(np.max(errs["rotation_raw_deg"]))
        out["mount_translation_error_mm"] = float(np.mean(errs["translation_mm"]))
        out["mount_translation_error_max_mm"] = float(np.max(errs["translation_mm"]))
    return out


def mount_errors(sync, studio) -> dict[str, np.ndarray]:
    """Each calibrated tracker's solved mount (``sync``: a SyncResult) against the simulated one
    (``studio``: :func:`~dualhuman_builder.sim.studio.simulate_studio` of the scene, same seed), in
    actor then tracker order: ``rotation_deg`` against the mount seen from the suit's reported
    (misaligned) segment frame, the one the data identify; ``rotation_raw_deg`` against the
    simulated mount itself; ``translation_mm`` the offset's error, also seen from that frame."""
    rot, raw, trans = [], [], []
    for k, a in enumerate(sync.actors):
        if a.mounts is None:
            continue
        st, su = studio.trackers[k], studio.suits[k]
        for j, serial in enumerate(a.serials):
            if not a.mounts.calibrated[j]:
                continue
            i = st.serials.index(serial)
            seg = MVN_SEGMENTS.index(st.segments[i])
            m_true = Rotation.from_quat(st.mount_rotation[i])
            misaligned = Rotation.from_quat(su.misalignment[seg])
            seen = misaligned.inv().apply(np.array(st.mount_translation[i], dtype=np.float64))  # a copy: scipy needs it writable
            est = Rotation.from_quat(a.mounts.rotations[j])
            rot.append(np.degrees(((misaligned.inv() * m_true).inv() * est).magnitude()))
            raw.append(np.degrees((m_true.inv() * est).magnitude()))
            trans.append(1000 * np.linalg.norm(np.asarray(a.mounts.translations[j]) - seen))
    return {"rotation_deg": np.array(rot), "rotation_raw_deg": np.array(raw), "translation_mm": np.array(trans)}

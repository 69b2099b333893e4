"""Contacts scored against ground truth.

* :func:`contacts_for_scene`: a check of the contacts stage on data whose every contact is known: the
  scene generator stores per-vertex signed distances within a band
  (:data:`~dualhuman_builder.sim.scenes.DISTANCE_BAND`), so the contacts stage run on the scene's own
  bodies must find the same vertices.
* :func:`take_fit_contacts` / :func:`fit_contact_scores`: the fitted pair's contacts against the
  ground truth's, both computed by the contacts stage's code at the contact threshold: per-vertex
  precision, recall and F1 per take and per body region, and the contact events' onset and offset
  errors (ms). Contact labels are what the toolkit's datasets are for, so this is a first-class
  accuracy figure next to the joint error.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dualhuman_builder.contacts.compute import (
    ContactResult,
    ContactTopology,
    compute_contacts,
)


def gt_frames(times_s: np.ndarray, gt_fps: float, n: int) -> np.ndarray:
    """Ground-truth frame index ``(T,)`` of each fitted frame time ``times_s`` (s) in a scene of ``n``
    frames at ``gt_fps``; the fit's frames must fall on the scene's (ValueError otherwise)."""
    idx = np.round(np.asarray(times_s) * gt_fps).astype(np.int64)
    if np.any(np.abs(idx / gt_fps - times_s) > 1e-6):
        raise ValueError("evaluate with the fit fps equal to the scene fps (frames must coincide)")
    return np.clip(idx, 0, n - 1)


def contacts_for_scene(scene, threshold_m: float | None = None, band_m: float | None = None,
                       topology: ContactTopology | None = None) -> tuple[ContactResult, dict[str, float]]:
    """Contacts of a ground-truth :class:`~dualhuman_builder.sim.scenes.Scene` (or a path to a
    saved one) and their precision, recall and F1 against the scene's own per-vertex contacts
    (:meth:`~dualhuman_builder.sim.scenes.Scene.contact_labels` at the same threshold). Defaults:
    :data:`~dualhuman_builder.sim.scenes.CONTACT_THRESHOLD` and
    :data:`~dualhuman_builder.sim.scenes.DISTANCE_BAND`."""
    from dualhuman_builder.sim.scenes import CONTACT_THRESHOLD, DISTANCE_BAND, Scene

    if isinstance(scene, (str, Path)):
        scene = Scene.load(scene)
    threshold = CONTACT_THRESHOLD if threshold_m is None else threshold_m
    band = DISTANCE_BAND if band_m is None else band_m
    if threshold > DISTANCE_BAND:
        raise ValueError(f"threshold_m {threshold} exceeds the scene's stored distance band {DISTANCE_BAND} m; "
                         "its reference labels cannot be compared")  # fmt: skip
    res = compute_contacts(scene.sequence, threshold, band, topology=topology)
    return res, res.f1(scene.contact_labels(threshold))


def label_scores(pred: np.ndarray, ref: np.ndarray) -> dict[str, float]:
    """Precision, recall and F1 of bool labels ``pred`` against the reference ``ref`` (same shape),
    with the counts ``tp``, ``fp``, ``fn``; each score is 1.0 when its denominator is empty (nothing
    to find, nothing claimed)."""
    pred, ref = np.asarray(pred, dtype=bool), np.asarray(ref, dtype=bool)
    if pred.shape != ref.shape:
        raise ValueError(f"labels {pred.shape} and reference {ref.shape} differ in shape")
    return count_scores(int(np.sum(pred & ref)), int(np.sum(pred & ~ref)), int(np.sum(~pred & ref)))


def count_scores(tp: int, fp: int, fn: int) -> dict[str, float]:
    """:func:`label_scores` from the counts of true positives ``tp``, false positives ``fp`` and false
    negatives ``fn`` (to pool counts over takes)."""
    return {"precision": tp / (tp + fp) if tp + fp else 1.0, "recall": tp / (tp + fn) if tp + fn else 1.0,
            "f1": 2 * tp / (2 * tp + fp + fn) if tp + fp + fn else 1.0, "tp": tp, "fp": fp, "fn": fn}  # fmt: skip


def _any_contact_events(frame_contact: np.ndarray, merge_gap: int) -> list[dict]:
    """The runs of ``frame_contact (T,)`` as events of the pseudo region pair ``("any", "any")``,
    runs separated by at most ``merge_gap`` frames merged (as :mod:`~dualhuman_builder.contacts.events`)."""
    on = np.flatnonzero(frame_contact)
    events: list[dict] = []
    for t in on:
        if events and t - events[-1]["end"] <= merge_gap:
            events[-1]["end"] = int(t) + 1
        else:
            events.append({"region_a": "any", "region_b": "any", "start": int(t), "end": int(t) + 1})
    return events


def event_timing(fitted: list[dict], truth: list[dict], fps: float) -> dict:
    """Onset and offset errors (ms) of the region-pair contact events ``fitted`` against ``truth``
    (:func:`~dualhuman_builder.contacts.events.contact_events` dicts, frame indices on one timeline of
    ``fps``). Each true event is matched to the fitted event of the same region pair that overlaps it
    most (the nearest onset when none overlaps within one second), each fitted event used once.
    Returns ``onset_ms``/``offset_ms`` (mean absolute error over matched events, NaN when none),
    ``onset_max_ms``/``offset_max_ms``, ``matched``, ``missed`` (true events with no match) and
    ``spurious`` (fitted events matched to none)."""
    free: dict[tuple, list[dict]] = {}
    for e in fitted:
        free.setdefault((e["region_a"], e["region_b"]), []).append(e)
    onsets, offsets, missed = [], [], 0
    reach = fps  # one second, in frames
    for g in sorted(truth, key=lambda e: e["end"] - e["start"], reverse=True):  # long events choose first
        cands = free.get((g["region_a"], g["region_b"]), [])
        best, key = None, None
        for e in cands:
            overlap = min(e["end"], g["end"]) - max(e["start"], g["start"])
            k = (overlap > 0, overlap, -abs(e["start"] - g["start"]))
            if (overlap > 0 or abs(e["start"] - g["start"]) <= reach) and (key is None or k > key):
                best, key = e, k
        if best is None:
            missed += 1
            continue
        cands.remove(best)
        onsets.append(abs(best["start"] - g["start"]) * 1000.0 / fps)
        offsets.append(abs(best["end"] - g["end"]) * 1000.0 / fps)
    nan = float("nan")
    mean, top = (lambda x: float(np.mean(x)) if x else nan), (lambda x: float(np.max(x)) if x else nan)
    return {"onset_ms": mean(onsets), "offset_ms": mean(offsets), "onset_max_ms": top(onsets), "offset_max_ms": top(offsets),
            "matched": len(onsets), "missed": missed, "spurious": sum(len(v) for v in free.values())}  # fmt: skip


def fit_contact_scores(fitted_vertices, truth_vertices, fps: float, threshold_m: float | None = None,
                       band_m: float | None = None, topology: ContactTopology | None = None,
                       merge_gap: int | None = None) -> dict:
    """Contacts of a fitted pair against the ground truth's, both computed by the contacts stage's own
    code (:func:`~dualhuman_builder.contacts.compute.contacts_from_vertices`) at ``threshold_m``
    (default :data:`~dualhuman_builder.sim.scenes.CONTACT_THRESHOLD`, 20 mm).

    ``fitted_vertices``, ``truth_vertices``: per actor ``(T, V, 3)`` vertices (world metres) on the same
    ``T`` frames of one timeline at ``fps``, actors in the same order. Returns per-vertex ``precision``,
    ``recall``, ``f1`` (and ``tp``/``fp``/``fn``) over both actors and every frame; ``regions``: the same
    per body region (:mod:`~dualhuman_builder.body.regions`; regions neither side has a contact on are
    left out), each region's vertices of both actors pooled; ``events``: :func:`event_timing` of the
    region-pair events, and ``any_events`` the same of the runs of frames with any contact;
    ``frames_in_contact`` and ``frames_in_contact_truth``."""
    from dualhuman_builder.contacts.compute import (
        DEFAULT_MERGE_GAP,
        contacts_from_vertices,
        default_topology,
    )
    from dualhuman_builder.sim.scenes import CONTACT_THRESHOLD, DISTANCE_BAND

    threshold = CONTACT_THRESHOLD if threshold_m is None else threshold_m
    band = DISTANCE_BAND if band_m is None else band_m
    gap = DEFAULT_MERGE_GAP if merge_gap is None else merge_gap
    topo = topology or default_topology()
    kw = {"threshold_m": threshold, "band_m": band, "merge_gap": gap, "fps": fps, "workers": 1}
    fit = contacts_from_vertices(fitted_vertices[0], fitted_vertices[1], topo, **kw)
    ref = contacts_from_vertices(truth_vertices[0], truth_vertices[1], topo, **kw)
    out: dict = label_scores(fit.labels, ref.labels)
    regions = {}
    for r, name in enumerate(topo.region_names):
        ids = np.flatnonzero(topo.vertex_region == r)
        s = label_scores(fit.labels[:, :, ids], ref.labels[:, :, ids])
        if s["tp"] + s["fp"] + s["fn"]:
            regions[name] = s
    out["regions"] = regions
    out["events"] = event_timing(fit.events, ref.events, fps)
    runs = [_any_contact_events(r.frame_contact, gap) for r in (fit, ref)]
    out["any_events"] = event_timing(runs[0], runs[1], fps)
    out["frames_in_contact"] = int(fit.frame_contact.sum())
    out["frames_in_contact_truth"] = int(ref.frame_contact.sum())
    return out


def take_fit_contacts(tf, scene, threshold_m: float | None = None, topology: ContactTopology | None = None) -> dict:
    """:func:`fit_contact_scores` of a fitted take ``tf`` (a :class:`~dualhuman_builder.fit.process.TakeFit`)
    against its ground-truth ``scene``, on the scene frames the fit's frames fall on (the fit's fps
    must equal the scene's, as for :func:`~dualhuman_builder.evaluation.fit.evaluate_take_fit`)."""

    gt = scene.sequence
    fit = tf.fit.sequence
    actors = fit.actors if hasattr(fit, "actors") else fit
    if len(actors) != 2 or len(gt.actors) != 2:
        raise ValueError(f"contacts need two actors; the fit has {len(actors)}, the scene {len(gt.actors)}")
    idx = gt_frames(tf.sync.times_s, gt.fps, gt.num_frames)
    return fit_contact_scores([a.vertices() for a in actors], [a.vertices()[idx] for a in gt.actors], gt.fps,
                              threshold_m=threshold_m, topology=topology)  # fmt: skip

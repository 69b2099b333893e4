"""Contacts stage: exact agreement with a brute-force libigl query, F1 against a ground-truth
scene's own contacts, the broad phase, region events, save/load, bad input and the workspace stage."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from dualhuman_builder.contacts import (ContactResult, ContactTopology, compute_contacts, contact_frame,
                                        contacts_from_vertices, run_contacts)  # fmt: skip
from dualhuman_builder.evaluation.contacts import contacts_for_scene
from dualhuman_builder.errors import FormatError, WorkspaceError

BAND = 0.05
THRESHOLD = 0.02


@pytest.fixture(scope="module")
def topo(body_model):
    return ContactTopology.for_model(body_model)


@pytest.fixture(scope="module")
def handshake():
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    return make_scene(SceneParams(type="handshake", seed=0, fps=7.5))


def _posed(model, offsets, shapes=(None, None), turn_b=math.pi):
    """Rest-pose bodies: A at the origin facing +Z, B turned ``turn_b`` about +Y at each offset
    ``(dx, dz)``. Returns ``(va, vb)`` each ``(len(offsets), V, 3)`` float32."""
    import torch

    n = len(offsets)
    pose = torch.zeros(n, model.num_bones, 3)
    with torch.no_grad():
        va = model.forward(pose, shapes[0], torch.tensor([[0.0, 0.95, 0.0]] * n)).vertices.numpy()
        pose[:, 0, 1] = turn_b
        vb = model.forward(pose, shapes[1], torch.tensor([[dx, 0.95, dz] for dx, dz in offsets])).vertices.numpy()
    return va, vb


@pytest.fixture(scope="module")
def hug(body_model):
    """Front-to-front bodies of two shapes: 15 cm apart (deepest overlap ~9 cm: vertices more than
    the band inside), 25 cm, and 22 cm with a sideways shift."""
    shapes = ({"gender": 0.0, "height": 0.6, "weight": 0.6}, {"gender": 1.0, "height": 0.4, "weight": 0.4})
    return _posed(body_model, [(0.0, 0.15), (0.0, 0.25), (0.08, 0.22)], shapes)


def _brute(P, Q, faces):
    """Brute force: every vertex against the whole closed mesh, no band."""
    import igl

    return igl.signed_distance(P.astype(np.float64), Q.astype(np.float64), faces,
                               sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0]  # fmt: skip


def _check_exact(topo, va, vb, frames):
    res = contacts_from_vertices(va, vb, topo, threshold_m=THRESHOLD, band_m=BAND)
    deep = compared = 0
    for t in frames:
        frame = contact_frame(topo, va[t], vb[t], BAND)
        for i, (P, Q) in enumerate(((va[t], vb[t]), (vb[t], va[t]))):
            S = _brute(P, Q, topo.faces)
            near = np.abs(S) <= BAND
            if frame is None:  # skipped as far apart: rightly so
                assert not near.any() and not res.labels[i, t].any()
                continue
            d, f = frame
            compared += int(near.sum())
            # possible contacts (and everything inside) are libigl's own answers on the sub-mesh;
            # the rest are computed on warp's closest face (float32 may pick a face tied to 1e-7 m)
            libigl = near & (S < THRESHOLD)
            np.testing.assert_allclose(d[i][libigl], S[libigl], rtol=0, atol=1e-9)
            np.testing.assert_allclose(d[i][near], S[near], rtol=0, atol=1e-7)
            np.testing.assert_array_equal(np.sign(d[i][near]), np.sign(S[near]))
            assert np.isnan(d[i][S > BAND]).all()
            assert np.isneginf(d[i][S < -BAND]).all()
            deep += int(np.sum(S < -BAND))
            assert (f[i][np.isfinite(d[i])] >= 0).all() and (f[i][~np.isfinite(d[i])] == -1).all()
            np.testing.assert_array_equal(res.labels[i, t], S < THRESHOLD)
            # the sequence loop (a pipeline over two selectors) stores what contact_frame returns
            np.testing.assert_array_equal(res.distances[i, t], d[i].astype(np.float16))
    assert compared > 200
    return res, deep


def test_banded_igl_is_nan_beyond_the_band(topo, hug):
    import igl

    P, Q = hug[0][1].astype(np.float64), hug[1][1].astype(np.float64)
    S, I, _, _ = igl.signed_distance(P, Q, topo.faces, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL,
                                     lower_bound=-BAND, upper_bound=BAND)  # fmt: skip
    full = _brute(P, Q, topo.faces)
    inside = np.abs(full) <= BAND
    assert np.isnan(S[~inside]).all() and np.isfinite(S[inside]).all()
    np.testing.assert_array_equal(S[inside], full[inside])


def test_exact_agreement_with_brute_force_on_a_hug(topo, hug):
    res, deep = _check_exact(topo, *hug, frames=[0, 1, 2])
    assert deep > 100  # the 15 cm frame has vertices deeper than the band: found by the flood fill
    assert res.stats["deep_vertices"] == deep
    # the sub-mesh query touches far fewer faces than the whole body on these frames
    assert res.stats["queried_faces"] < 2 * 3 * len(topo.faces)


def test_exact_agreement_with_brute_force_on_a_handshake(topo, handshake):
    va, vb = (a.vertices() for a in handshake.sequence.actors)
    gt = handshake.contact_labels()
    touching = np.flatnonzero(gt[0].any(1))
    approach = int(touching[0]) - 1  # hands near, not yet touching
    assert contact_frame(topo, va[approach], vb[approach], BAND) is not None
    res, _ = _check_exact(topo, va, vb, frames=[approach - 1, approach, int(touching[0]), int(touching[len(touching) // 2])])
    assert not res.frame_contact[approach] and res.frame_contact[touching[0]]


def test_f1_against_the_scenes_own_contacts(topo, handshake):
    res, score = contacts_for_scene(handshake, topology=topo)
    assert score["tp"] > 1000
    assert score["f1"] >= 0.95 and score["precision"] >= 0.95 and score["recall"] >= 0.95
    gt = handshake.contact_labels()
    gt_frames = gt[0].any(1) | gt[1].any(1)
    assert np.mean(res.frame_contact == gt_frames) >= 0.95
    # the handshake is one right-hand-to-right-hand event spanning the contact frames
    hands = [e for e in res.events if (e["region_a"], e["region_b"]) == ("right_hand", "right_hand")]
    assert len(hands) == 1
    ev = hands[0]
    contact = np.flatnonzero(res.frame_contact)
    assert (ev["start"], ev["end"]) == (contact[0], contact[-1] + 1)
    assert ev["end_s"] == pytest.approx(ev["end"] / 7.5, abs=1e-6)
    assert 0 < ev["min_distance_m"] < THRESHOLD and ev["peak_vertices"] >= res.contact_counts().max(1).min()
    # most of both bodies lies beyond the band: the broad phase queries a small part of them
    assert res.stats["queried_vertices"] < 0.25 * 2 * res.num_frames * topo.num_vertices
    assert res.stats["skipped_far_frames"] > 0


@pytest.mark.slow
def test_worker_processes_give_the_same_result(topo, hug, tmp_path, monkeypatch):
    """Frames spread over two worker processes (interleaved): the same labels, distances, events
    and query counts as in one process; progress reaches 100 %; the temporary folder is removed."""
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    va, vb = (np.concatenate([v, v[::-1]]) for v in hug)  # 6 frames, far one in the middle
    vb[2] += np.float32(3.0)
    one = contacts_from_vertices(va, vb, topo, workers=1)
    messages = []
    two = contacts_from_vertices(va, vb, topo, workers=2, progress=messages.append)
    assert one.stats["workers"] == 1 and two.stats["workers"] == 2
    np.testing.assert_array_equal(two.labels, one.labels)
    np.testing.assert_array_equal(two.distances, one.distances)
    assert two.events == one.events and one.labels.any()
    for key in ("queried_vertices", "queried_faces", "deep_vertices", "skipped_far_frames"):
        assert two.stats[key] == one.stats[key], key
    assert one.stats["skipped_far_frames"] == 1
    assert messages[0] == "contacts: 6 frames in 2 worker processes" and messages[-1].endswith("6/6 frames (100 %)")
    assert list(tmp_path.iterdir()) == []
    from dualhuman_builder.contacts.workers import MIN_FRAMES_PER_WORKER, auto_workers

    assert auto_workers(MIN_FRAMES_PER_WORKER * 2 - 1, cpus=8) == 1  # short: stays in this process
    assert auto_workers(MIN_FRAMES_PER_WORKER * 2, cpus=8) == 2
    assert auto_workers(100_000, cpus=4) == 2 and auto_workers(100_000, cpus=64) == 8
    assert auto_workers(100_000, cpus=2) == 1  # one process already uses both CPUs


def test_a_failing_worker_is_reported(topo, hug, tmp_path, monkeypatch):
    import sys
    import tempfile

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path))
    monkeypatch.setattr(sys, "executable", "/bin/false")  # the worker interpreter exits 1 at once
    with pytest.raises(RuntimeError, match=r"contacts worker \d of 2 failed \(exit status 1\)"):
        contacts_from_vertices(*hug, topo, workers=2)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="workers must be a whole number >= 1"):
        contacts_from_vertices(*hug, topo, workers=0)


def test_far_apart_bodies_are_skipped_without_a_query(topo, hug):
    va, vb = hug
    res = contacts_from_vertices(va, vb + np.array([3.0, 0.0, 0.0], np.float32), topo)
    assert res.stats["queried_vertices"] == 0 and res.stats["queried_faces"] == 0
    assert res.stats["skipped_far_frames"] == 3
    assert not res.labels.any() and not res.frame_contact.any() and res.events == []
    assert np.isnan(res.distances.astype(np.float32)).all()
    assert contact_frame(topo, va[0], vb[0] + 3.0) is None


def test_narrow_phase_keeps_what_libigl_needs_at_exact_ties():
    """Two parallel slabs 6 cm apart; query points on the plane midway between them are exactly
    3 cm from both (a tie the float32 narrow phase cannot break), others scattered near and far;
    at the origin and 1 km from it. Every point within the band is selected, none beyond band +
    slack, and libigl on the selected faces returns what it returns on the whole mesh, value and
    sign (to 1e-12 m)."""
    import igl
    import trimesh

    from dualhuman_builder.geometry.narrow import NearSelector

    slabs = [trimesh.creation.box(extents=(0.4, 0.02, 0.4)) for _ in range(2)]
    slabs[0].apply_translation((0.0, -0.04, 0.0))
    slabs[1].apply_translation((0.0, 0.04, 0.0))
    mesh = trimesh.util.concatenate(slabs).subdivide().subdivide()
    V, F = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    rng = np.random.default_rng(0)
    mid = np.c_[rng.uniform(-0.15, 0.15, 200), np.zeros(200), rng.uniform(-0.15, 0.15, 200)]
    scattered = rng.uniform([-0.3, -0.2, -0.3], [0.3, 0.2, 0.3], (2000, 3))
    sel = NearSelector(F, V)
    # also 1 km from the world origin, where a float32 coordinate alone rounds by 3e-5 m (> the slack)
    for shift in (np.zeros(3), np.array([1000.0, 0.0, -1000.0])):
        P, Vs = np.concatenate([mid, scattered]) + shift, V + shift
        near, faces = sel.select(0, P, Vs, BAND)
        full = igl.signed_distance(P, Vs, F, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0]
        within = np.flatnonzero(np.abs(full) <= BAND)
        assert set(within) <= set(near) and np.abs(full[near]).max() <= BAND + 2 * sel.slack
        assert set(range(200)) <= set(near)  # the ties
        assert 0 < len(faces) < len(F)
        sub = F[faces]
        S = igl.signed_distance(P[near], Vs, sub, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL, lower_bound=-BAND,
                                upper_bound=BAND)[0]  # fmt: skip
        ok = np.isfinite(S)
        np.testing.assert_array_equal(ok, np.abs(full[near]) <= BAND)
        np.testing.assert_allclose(S[ok], full[near][ok], rtol=0, atol=1e-12)


@pytest.fixture(scope="module")
def side_by_side(body_model):
    """Ten frames of two identical A-posed bodies side by side facing +Z: B's right hand 1 cm from
    A's left hand on frames 2-4 and 6-7, 3 m away otherwise."""
    va, vb = _posed(body_model, [(0.0, 0.0)], turn_b=0.0)
    x = va[0][:, 0]
    touch = vb[0] + np.array([x.max() - x.min() + 0.01, 0.0, 0.0], np.float32)
    far = vb[0] + np.array([3.0, 0.0, 0.0], np.float32)
    on = [2, 3, 4, 6, 7]
    return np.repeat(va, 10, axis=0), np.stack([touch if t in on else far for t in range(10)]), on


def test_events_start_and_end_on_a_constructed_case(topo, side_by_side):
    va, vb, on = side_by_side
    messages = []
    res = contacts_from_vertices(va, vb, topo, merge_gap=0, fps=10.0, progress=messages.append)
    assert len(messages) == 10 and messages[-1] == "contacts: 10/10 frames (100 %)"
    np.testing.assert_array_equal(np.flatnonzero(res.frame_contact), on)
    assert res.stats["skipped_far_frames"] == 5
    pairs = {(e["region_a"], e["region_b"]) for e in res.events}
    assert ("left_hand", "right_hand") in pairs and all("hand" in a or "hand" in b for a, b in pairs)
    hand = [e for e in res.events if (e["region_a"], e["region_b"]) == ("left_hand", "right_hand")]
    assert [(e["start"], e["end"], e["contact_frames"]) for e in hand] == [(2, 5, 3), (6, 8, 2)]
    assert hand[0]["start_s"] == 0.2 and hand[0]["end_s"] == 0.5
    assert hand[0]["min_distance_m"] == pytest.approx(np.nanmin(res.distances[:, 2].astype(np.float64)), abs=1e-3)
    # a one-frame gap is merged by default: one event [2, 8) with 5 contact frames
    merged = contacts_from_vertices(va, vb, topo)
    hand = [e for e in merged.events if (e["region_a"], e["region_b"]) == ("left_hand", "right_hand")]
    assert [(e["start"], e["end"], e["contact_frames"]) for e in hand] == [(2, 8, 5)]
    assert "start_s" not in hand[0]  # no fps given


def test_save_load_round_trip(topo, side_by_side, tmp_path):
    va, vb, _ = side_by_side
    res = contacts_from_vertices(va, vb, topo, fps=10.0, actors=("ann", "bob"))
    path = res.save(tmp_path / "contacts.npz")
    back = ContactResult.load(path)
    np.testing.assert_array_equal(back.labels, res.labels)
    np.testing.assert_array_equal(back.distances, res.distances)  # NaNs in the same places
    np.testing.assert_array_equal(back.frame_contact, res.frame_contact)
    assert back.events == res.events and back.stats == res.stats
    assert back.actors == ("ann", "bob") and back.region_names == topo.region_names
    assert back.f1(res.labels)["f1"] == 1.0
    # labels are bit-packed: 1 bit per vertex
    with np.load(path) as z:
        assert z["labels_packed"].shape == (2, 10, math.ceil(topo.num_vertices / 8))
    (tmp_path / "other.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError, match="not a readable"):
        ContactResult.load(tmp_path / "other.npz")


def test_f1_counts(topo, side_by_side):
    va, vb, _ = side_by_side
    res = contacts_from_vertices(va[:3], vb[:3], topo)
    ref = res.labels.copy()
    t, v = np.argwhere(ref[0])[0]
    ref[0, t, v] = False  # one false positive
    ref[1, 0, 0] = True  # one false negative
    s = res.f1((ref[0], ref[1]))
    assert (s["fp"], s["fn"], s["tp"]) == (1, 1, int(res.labels.sum()) - 1)
    assert s["f1"] == pytest.approx(2 * s["tp"] / (2 * s["tp"] + 2))
    with pytest.raises(ValueError, match="shape"):
        res.f1(ref[:, :2])


def test_nan_vertices_are_skipped_or_raise(topo, side_by_side):
    va, vb, on = side_by_side
    clean = contacts_from_vertices(va, vb, topo)
    va = va.copy()
    va[3, 100] = np.nan
    res = contacts_from_vertices(va, vb, topo)
    assert res.stats["skipped_nan_frames"] == 1 and res.stats["first_nan_frames"] == [3]
    assert not res.valid[3] and res.valid.sum() == 9 and not res.labels[:, 3].any()
    keep = np.arange(10) != 3
    np.testing.assert_array_equal(res.labels[:, keep], clean.labels[:, keep])
    with pytest.raises(ValueError, match="verts_a holds NaN or infinite coordinates at frame 3"):
        contacts_from_vertices(va, vb, topo, nan_policy="raise")
    with pytest.raises(ValueError, match="every one of the 2 frames"):
        contacts_from_vertices(np.full((2, topo.num_vertices, 3), np.nan), vb[:2], topo)
    with pytest.raises(ValueError, match="verts_b holds NaN"):
        contact_frame(topo, vb[0], va[3])


def test_bad_input_is_named(topo, side_by_side):
    va, vb, _ = side_by_side
    V = topo.num_vertices
    cases = [
        ((va[0], vb), {}, r"verts_a must have shape \(T, V, 3\)"),
        ((va[:, :100], vb[:, :100]), {}, f"100 vertices per frame; the mesh topology has {V}"),
        ((va[:0], vb[:0]), {}, "no frames"),
        ((va[:3], vb[:2]), {}, "must have the same shape"),
        ((va, vb), {"threshold_m": 0.0}, "threshold_m must be a positive"),
        ((va, vb), {"threshold_m": 0.03, "band_m": 0.02}, "band_m must be finite and at least threshold_m"),
        ((va, vb), {"band_m": float("nan")}, "band_m must be finite"),
        ((va, vb), {"merge_gap": -1}, "merge_gap must be a non-negative"),
        ((va, vb), {"nan_policy": "ignore"}, "nan_policy must be"),
    ]
    for args, kw, msg in cases:
        with pytest.raises(ValueError, match=msg):
            contacts_from_vertices(*args, topo, **kw)
    with pytest.raises(ValueError, match="no fitted bodies.*fit stage"):
        compute_contacts(None)
    with pytest.raises(ValueError, match="expected an InteractionSequence"):
        compute_contacts(va)
    with pytest.raises(ValueError, match=r"faces must have shape \(F, 3\)"):
        ContactTopology(np.zeros((0, 3), int), V, topo.vertex_region, topo.region_names, topo.reference_vertices)
    with pytest.raises(ValueError, match="only 2 names"):
        ContactTopology(topo.faces, V, topo.vertex_region, ("a", "b"), topo.reference_vertices)


def _short_sequence(scene, frames):
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    seq = scene.sequence
    tracks = [BodyTrack(pose=a.pose[frames], transl=a.transl[frames], shape=a.shape, fps=a.fps, bone_names=a.bone_names,
                        shape_names=a.shape_names, model=a.model, model_version=a.model_version, actor=a.actor)
              for a in seq.actors]  # fmt: skip
    return InteractionSequence(tuple(tracks), take="T1")


def test_workspace_stage_end_to_end(ws, handshake):
    gt = handshake.contact_labels()
    first = int(np.flatnonzero(gt[0].any(1))[0])
    seq = _short_sequence(handshake, slice(first - 2, first + 3))  # 2 frames apart, 3 touching
    ws.add_take("T1")
    with pytest.raises(WorkspaceError, match="no fitted bodies: its fit stage has not run") as err:
        run_contacts(ws, "T1", log=lambda m: None)
    assert f"dualhuman fit {ws.root} --take T1" in str(err.value)
    assert ws.stage_record("contacts", "T1") is None  # nothing was started
    ws.run_stage("fit", lambda out: seq.save(out.path("bodies.npz")) and None, take="T1")

    logs: list[str] = []
    r = run_contacts(ws, "T1", log=logs.append)
    assert not r.skipped and set(r.artifacts) == {"contacts.npz", "contacts.json"}
    assert r.summary["frames"] == 5 and r.summary["contact_frames"] == 3 and r.summary["events"] >= 1
    assert any("frames in contact" in m for m in logs)
    res = ContactResult.load(r.artifacts["contacts.npz"])
    np.testing.assert_array_equal(res.frame_contact, [False, False, True, True, True])
    report = json.loads(r.artifacts["contacts.json"].read_text())
    assert report["events"] == res.events and report["stats"]["band_m"] == BAND
    assert report["contact_vertices"][res.actors[0]] == res.contact_counts()[0].tolist()
    assert ("right_hand", "right_hand") in {(e["region_a"], e["region_b"]) for e in report["events"]}
    # up to date: nothing runs; a new threshold re-runs
    assert run_contacts(ws, "T1", log=logs.append).skipped
    r3 = run_contacts(ws, "T1", threshold_m=0.005, log=logs.append)
    assert not r3.skipped and r3.summary["contact_frames"] <= 3
    with pytest.raises(ValueError, match="band_m must be finite and at least threshold_m"):
        run_contacts(ws, "T1", threshold_m=0.1, log=logs.append)
    with pytest.raises(WorkspaceError, match="no take 'T9'"):
        run_contacts(ws, "T9", log=logs.append)

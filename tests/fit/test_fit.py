"""Fuse, shape calibration and the joint fit, down to a small simulated take recorded through real
loopback transports (simulated devices -> UDP/pty/virtual CAN -> MCAP -> sync -> fuse -> fit)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import roma
import torch

from dualhuman_builder.body.model import get_body_model
from dualhuman_builder.fit.calibrate import CalibrationError, calibrate_shape
from dualhuman_builder.fit.fitter import FitConfig, FitError, fit_actors
from dualhuman_builder.fit.skeleton import BodyRig, rotvec_to_rotmat
from dualhuman_builder.sync.timeline import SyncError, synchronise


@pytest.fixture(scope="module")
def model():
    return get_body_model()


SHAPE = {"gender": 0.2, "height": 0.7, "weight": 0.3}


def _rig_and_pose(model, seed: int):
    """A BodyRig of :data:`SHAPE` and three random frames: segment rotations (3, 23, 3, 3), translations (3, 3)."""
    torch.manual_seed(seed)
    return BodyRig(model, SHAPE), roma.rotvec_to_rotmat(torch.randn(3, 23, 3) * 0.5), torch.randn(3, 3)


def test_rotvec_to_rotmat_is_roma_with_one_node():
    """The fit's fused rotation-vector conversion gives roma's matrices and gradients (float64, to
    1e-10), at zero, tiny, 0.05 rad and near-pi angles too, and its closed-form gradient passes
    torch's numerical check; in float32 it agrees to float rounding; a second derivative raises."""
    g = torch.Generator().manual_seed(3)
    v = torch.randn(40, 3, generator=g, dtype=torch.float64) * 0.5
    v[0] = 0.0
    v[1] = torch.tensor([1e-8, -2e-8, 0.0])
    v[2] = torch.tensor([0.0499, 0.001, 0.0])
    v[3] = torch.tensor([0.0501, 0.0, 0.0])
    v[4] = torch.tensor([0.0, 3.1, 0.2])
    w = torch.randn(40, 3, 3, generator=g, dtype=torch.float64)
    mine, theirs = v.clone().requires_grad_(True), v.clone().requires_grad_(True)
    (rotvec_to_rotmat(mine) * w).sum().backward()
    (roma.rotvec_to_rotmat(theirs) * w).sum().backward()
    assert torch.allclose(rotvec_to_rotmat(v), roma.rotvec_to_rotmat(v), atol=1e-10)
    assert torch.allclose(mine.grad[1:], theirs.grad[1:], atol=1e-7)  # roma's first-order branch at 1e-8
    assert torch.allclose(mine.grad[5:], theirs.grad[5:], atol=1e-10)
    assert torch.autograd.gradcheck(rotvec_to_rotmat, (v[:8].clone().requires_grad_(True),))
    r32 = rotvec_to_rotmat(v.float().reshape(4, 10, 3))
    assert r32.shape == (4, 10, 3, 3) and r32.dtype == torch.float32
    assert (r32.double().reshape(40, 3, 3) - roma.rotvec_to_rotmat(v)).abs().max() < 1e-6
    twice = v[5:8].clone().requires_grad_(True)
    (g1,) = torch.autograd.grad((rotvec_to_rotmat(twice) * w[5:8]).sum(), twice, create_graph=True)
    with pytest.raises(RuntimeError):  # first derivatives only, said loudly (not silently missing terms)
        g1.sum().backward()


def test_body_rig_is_anny_exactly(model):
    rig, A, transl = _rig_and_pose(model, 0)
    mine = rig.pose(A, transl)
    ref = model.forward(rig.local_pose(A), rig.shape, transl)
    assert (mine.heads - ref.bone_heads).abs().max() < 1e-5
    assert (mine.vertices - ref.vertices).norm(dim=-1).max() < 1e-5
    rig.add_subset("some", [0, 100, 5000])
    sub = rig.pose(A, transl, "some").vertices
    assert torch.allclose(sub, ref.vertices[:, [0, 100, 5000]], atol=1e-5)
    # scattered (frame, vertex) pairs, as the collision term reads them
    f, v = torch.tensor([2, 0, 1, 2]), torch.tensor([13000, 7, 7, 0])
    assert torch.allclose(rig.skin_at(mine, f, v), ref.vertices[f, v], atol=1e-5)
    # ... with the gradient of the whole mesh's skinning, fingers opened (a finger vertex among them)
    A.requires_grad_(True)
    opening = torch.tensor([[0.5, 1.0, 0.0, -0.3]] * 3, requires_grad=True)
    finger = int(np.flatnonzero(model.vertex_bone() == model.bone_index("finger2-3.L"))[0])
    f, v = torch.tensor([2, 0, 1, 2, 1]), torch.tensor([13000, 7, 7, 0, finger])
    w = torch.randn(len(f), 3)
    posed = rig.pose(A, transl, False, opening)
    ga = torch.autograd.grad((rig.skin_at(posed, f, v) * w).sum(), (A, opening))
    gb = torch.autograd.grad((rig.pose(A, transl, True, opening).vertices[f, v] * w).sum(), (A, opening))
    assert ga[1].abs().max() > 1e-3
    for x, y in zip(ga, gb):
        assert torch.allclose(x, y, atol=1e-5)
    # on the CPU in float32 skin_at runs two warp kernels (_SkinAt): the same values and gradients as its
    # tensor operations, repeated pairs adding up
    f2, v2 = f.repeat(40), v.repeat(40)
    w2 = torch.randn(len(f2), 3)
    fused = rig.skin_at(rig.pose(A, transl, False, opening), f2, v2)
    assert type(fused.grad_fn).__name__ == "_SkinAtBackward"
    gf = torch.autograd.grad((fused * w2).sum(), (A, opening))
    again = torch.autograd.grad((rig.skin_at(rig.pose(A, transl, False, opening), f2, v2) * w2).sum(), (A, opening))
    assert all(torch.equal(x, y) for x, y in zip(gf, again))  # the kernels' sums repeat exactly
    plain = rig._skin_at_torch(rig.pose(A, transl, False, opening), f2, v2)
    gt = torch.autograd.grad((plain * w2).sum(), (A, opening))
    assert (fused - plain).abs().max() < 1e-6
    for x, y in zip(gf, gt):
        assert (x - y).abs().max() < 1e-4 * y.abs().max()
    # which hand's openings move each vertex
    assert rig.opening_groups[finger] == 1 and rig.opening_groups[v[0]] == 0 and rig.opening_vertices[finger]
    assert set(np.unique(rig.opening_groups)) == {0, 1, 2}
    assert (rig.retarget(rig.segment_frames(A)) - A).abs().max() < 1e-5
    # without gradient the whole mesh is skinned over each vertex's nonzero weights (BodyRig._skin_sparse)
    with torch.no_grad():
        sparse = rig.pose(A, transl, True, opening).vertices
    assert rig._nz_wp is not None and sparse.shape == (3, rig.num_vertices, 3)
    assert (sparse - rig.pose(A, transl, True, opening).vertices).abs().max() < 1e-5  # anny's kernel, with gradient


def test_the_skeleton_terms_linear_pose_is_the_rigs_pose(model):
    """:meth:`BodyRig.pose_linear` (one matrix product) gives the heads and skinned vertices that
    :meth:`BodyRig.pose` gives, whatever the hands' openings, with the same gradient; bones or
    vertices the openings move are refused."""
    from dualhuman_builder.fit.skeleton import sole_vertices

    rig, A, transl = _rig_and_pose(model, 1)
    A.requires_grad_(True)
    soles = sole_vertices(model)
    ids = np.r_[soles["L"], soles["R"], [0, 100, 5000]]
    bones = np.r_[model.joint22_index.numpy(), rig.segment_bones.numpy()]
    rig.add_linear("terms", bones, ids)
    heads, verts = rig.pose_linear(A, transl, "terms")
    assert heads.shape == (3, len(bones), 3) and verts.shape == (3, len(ids), 3)
    ref = rig.pose(A, transl, opening=torch.tensor([[0.0] * 4, [1.0] * 4, [0.3, -0.2, 0.8, 0.5]]))
    assert (heads - ref.heads[:, bones]).abs().max() < 1e-5
    assert (verts - ref.vertices[:, ids]).abs().max() < 1e-5
    g = torch.autograd.grad((heads.sum() + verts.pow(2).sum()), A)[0]
    g_ref = torch.autograd.grad((ref.heads[:, bones].sum() + ref.vertices[:, ids].pow(2).sum()), A)[0]
    assert g.abs().max() > 0.1 and torch.allclose(g, g_ref, atol=1e-4)
    finger = [i for i, n in enumerate(model.bone_names) if n.startswith("finger2-2.L")][0]
    tip = int(np.flatnonzero(model.vertex_bone() == finger)[0])
    with pytest.raises(ValueError, match="hand openings"):
        rig.add_linear("bad", bones, [tip])
    with pytest.raises(ValueError, match="hand openings"):
        rig.add_linear("bad", [finger], ids)


def test_hand_opening_is_anny_and_the_scenes_flat_hand(model):
    from dualhuman_builder.body.hands import OPENINGS
    from dualhuman_builder.sim.performer import Performer

    rig, A, transl = _rig_and_pose(model, 2)
    opening = torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, 1.0, 1.0], [0.3, -0.2, 0.8, 0.5]], requires_grad=True)
    mine = rig.pose(A, transl, opening=opening)
    ref = model.forward(rig.local_pose(A, opening), rig.shape, transl)
    assert (mine.vertices - ref.vertices).norm(dim=-1).max() < 1e-5
    assert (mine.heads - ref.bone_heads).abs().max() < 1e-5
    plain = rig.pose(A, transl)
    names = model.bone_names
    thumb_l = [i for i, n in enumerate(names) if n.startswith("finger1-") and n.endswith(".L")]
    moved = (mine.vertices - plain.vertices).norm(dim=-1)  # (3, V)
    assert moved[0].max() < 1e-6  # opening 0 is the relaxed hand
    assert moved[1].max() > 0.02  # flat: fingertips move by centimetres ...
    vb = torch.as_tensor(model.vertex_bone())
    hand = [i for i, n in enumerate(names) if n.startswith(("finger", "metacarpal", "wrist"))]
    assert moved[1][~torch.isin(vb, torch.as_tensor(hand))].max() < 1e-6  # nothing but the hands
    assert (mine.heads[1, thumb_l[1:]] - plain.heads[1, thumb_l[1:]]).norm(dim=-1).min() > 0.005  # ... the thumb too
    # each slot moves its own bones and has a gradient there
    mine.vertices[2, vb == thumb_l[-1]].sum().backward()
    assert opening.grad[2, OPENINGS.index("thumb.L")] != 0 and opening.grad[2, OPENINGS.index("fingers.R")] == 0
    # opening 1 is the pose the scenes give a palm resting on the partner
    perf = Performer(model, SHAPE)
    local = torch.eye(3, dtype=torch.float64).repeat(1, len(names), 1, 1)
    for side in ("L", "R"):
        for bone, rot in perf.flat_hand[side].items():
            local[0, bone] = torch.as_tensor(rot)
    flat = model.forward(local.float(), rig.shape, torch.zeros(1, 3)).vertices[0]
    eye = torch.eye(3).expand(1, 23, 3, 3)
    ours = rig.pose(eye, torch.zeros(1, 3), opening=torch.ones(1, 4)).vertices[0]
    assert (ours - flat).norm(dim=-1).max() < 1e-5


@pytest.mark.slow
def test_shape_calibration_recovers_the_skeleton(model):
    from dualhuman_builder.sim.groundtruth import segment_kinematics
    from dualhuman_builder.tracks import BodyTrack

    truth = {"gender": 1.0, "age": 0.8, "muscle": 0.35, "weight": 0.55, "height": 0.38, "proportions": 0.57}
    torch.manual_seed(1)  # poses of the suit-driven bones (the others follow them, as on a suit)
    pose = BodyRig(model, truth).local_pose(roma.rotvec_to_rotmat(torch.randn(12, 23, 3) * 0.3)).numpy()
    track = BodyTrack.from_model(model, pose, np.tile([0.0, 0.95, 0.0], (12, 1)), model.shape_tensor(truth).numpy(), 30.0)
    sk = segment_kinematics(track)
    cal = calibrate_shape(model, np.array(sk.orientations), np.array(sk.positions), np.ones(12, bool))
    j_fit = model.rest(model.shape_tensor(cal.shape)).joints[0]
    j_true = model.rest(model.shape_tensor(truth)).joints[0]
    assert (j_fit - j_true).norm(dim=-1).mean() < 0.002  # under 2 mm at rest
    assert cal.rms_mm < 1.0 and cal.frames_used == 12
    with pytest.raises(CalibrationError, match="only 3 valid suit frames"):
        calibrate_shape(model, np.array(sk.orientations)[:3], np.array(sk.positions)[:3], np.ones(3, bool))


def test_bad_input_gets_clear_errors(model):
    with pytest.raises(SyncError, match="no suit stream"):
        synchronise({})
    with pytest.raises(FitError, match="no actors"):
        fit_actors(model, [], 30.0)


@pytest.fixture(scope="module")
def recorded(tmp_path_factory, model):
    from dualhuman_builder.evaluation.fit import record_simulated_take

    return record_simulated_take("handshake", 1, tmp_path_factory.mktemp("take"), fps=15.0, speed=1.0, model=model)


@pytest.mark.slow
def test_full_path_on_a_simulated_take(recorded, model):
    from dualhuman_builder.evaluation.fit import evaluate_take_fit
    from dualhuman_builder.fit.process import process_take

    take, scene = recorded
    tf = process_take(take, fps=15.0, model=model)
    ev = evaluate_take_fit(tf, scene, seed=1, model=model)
    # measured figures are in the closing note; these bounds hold with margin on this take
    assert ev["frames"] >= 55
    assert ev["mpjpe_mm"] < 12 and ev["root_mm"] < 12
    # the heading search (sync/mount.py) trades ~1 deg of mount yaw for the body's accuracy: the
    # issue's 1-degree goal is not met now (README, fit accuracy); a mis-solved heading is 5-6 degrees
    assert ev["mount_rotation_error_deg"] < 2.5
    assert ev["clock_offset_error_ms"] < 5.0
    assert ev["foot_slide_mm"] < 5.0
    # the pair ends within the 5 mm, and no deeper than the skeleton pass left it where that was over
    # the collision tolerance (2 mm; how much the hands overlap before the passes depends on the recording's
    # timing and the tracker offsets: 0.9-20 mm; the collision passes have their own tests below)
    assert ev["max_penetration_mm"] < 5.0, tf.fit.summary
    assert ev["max_penetration_mm"] <= max(ev["max_penetration_before_mm"], 2.0), tf.fit.summary
    assert ev["penetrating_share"] <= max(ev["penetrating_share_before"], 0.0005)
    opening = np.stack([tf.fit.frames[f"hand opening (0 relaxed, 1 flat)/{a}"] for a in ("sim-a", "sim-b")])
    assert opening.shape == (2, ev["frames"]) and opening.max() <= 1.01, opening.max(1)
    # the suit gives no fingers: where the skeleton pass leaves the clasped hands overlapping (it does with sync's
    # own tracker offsets on this take), the collision passes open them, within the openings' range
    raw = process_take(take, fps=15.0, config=FitConfig(sigma_suit_skeleton_m=0.0), model=model)
    assert raw.fit.summary["max_penetration_before_mm"] > 2.5, raw.fit.summary
    opening = np.stack([raw.fit.frames[f"hand opening (0 relaxed, 1 flat)/{a}"] for a in ("sim-a", "sim-b")])
    assert 0.05 < opening.max() <= 1.01, opening.max(1)
    seq = tf.fit.sequence
    assert [t.actor for t in seq.actors] == ["sim-a", "sim-b"] and seq.num_frames == ev["frames"]
    assert np.isfinite(np.asarray(seq.actors[0].pose)).all()
    # without trackers the suit's position drift stays in the root: fusion buys accuracy
    free = process_take(take, fps=15.0, use_trackers=False, config=FitConfig(collision=False), model=model)
    assert not any(f.fused_with_trackers for f in free.fused)
    ev_free = evaluate_take_fit(free, scene, seed=1, model=model)
    assert ev_free["root_mm"] > ev["root_mm"]


@pytest.mark.slow
def test_sync_warns_when_the_heading_or_the_root_is_uncertain(recorded, monkeypatch):
    """The sync report carries each actor's heading and its 1-sigma, and warns (naming the actor
    and the calibration take to carry mounts from) exactly when the 1-sigma exceeds ``HEADING_WARN_DEG``;
    likewise for the trackers' shared offset (where the root sits in the body) over
    ``COMMON_OFFSET_WARN_MM``: the handshake's actors turn too few segments to pin it (~14 mm)."""
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.sync import timeline

    take, _ = recorded
    columns = read_columns(take)

    def heading_warnings(report):
        return [w for w in report.get("warnings", []) if "--mounts-from" in w and ": heading" in w]

    def offset_warnings(report):
        return [w for w in report.get("warnings", []) if "--mounts-from" in w and "shared offset" in w]

    report = synchronise(columns, fps=15.0).report
    stds = {name: h["std_deg"] for name, h in report["heading"].items()}
    assert sorted(stds) == ["sim-a", "sim-b"] and all(s is not None and 0 < s for s in stds.values())
    assert len(heading_warnings(report)) == sum(s > timeline.HEADING_WARN_DEG for s in stds.values())
    # with a threshold below every 1-sigma, each actor is warned about, by name and figure
    monkeypatch.setattr(timeline, "HEADING_WARN_DEG", 0.5 * min(stds.values()))
    warned = heading_warnings(synchronise(columns, fps=15.0).report)
    assert len(warned) == 2
    for name, std in stds.items():
        assert any(w.startswith(f"{name}: heading") and f"{std:.1f} deg" in w for w in warned), warned
    offsets = {name: c["std_mm"] for name, c in report["common_offset"].items()}
    assert all(s > timeline.COMMON_OFFSET_WARN_MM for s in offsets.values()), offsets
    for name, std in offsets.items():
        assert any(w.startswith(f"{name}: the trackers' shared offset") and f"{std:.1f} mm" in w
                   for w in offset_warnings(report)), report["warnings"]
    monkeypatch.setattr(timeline, "COMMON_OFFSET_WARN_MM", 2 * max(offsets.values()))
    assert offset_warnings(synchronise(columns, fps=15.0).report) == []


@pytest.mark.slow
def test_a_calibration_takes_mounts_carry_over_to_later_takes(recorded, model, tmp_path):
    """``dualhuman sync WS --take T --mounts-from CAL``: the studio day's calibration take (the same
    simulated devices, seed 1) is synced first, and every tracker of the handshake keeps the mount
    solved there. The handshake's actors hardly turn a segment, so their heading and the trackers'
    shared offset otherwise rest on the sites' prior (~14 mm); carried, the shared offset is known
    to a few millimetres and each mounting rotation to the calibration's accuracy."""
    from click.testing import CliRunner

    from dualhuman_builder import cli
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.evaluation.fit import mount_errors, record_simulated_take
    from dualhuman_builder.sim.studio import simulate_studio
    from dualhuman_builder.sync.lag import LagEstimate, with_carried_lag
    from dualhuman_builder.sync.timeline import SyncResult
    from dualhuman_builder.workspace import Workspace

    take, scene = recorded
    cal_take, _ = record_simulated_take("calibration", 1, tmp_path / "cal", fps=15.0, model=model)  # the same devices
    ws_root = tmp_path / "ws"
    with Workspace.init(ws_root) as ws:
        ws.add_take("CAL", files=[cal_take])
        ws.add_take("SHAKE", files=[take])

    def run(*args):
        return CliRunner().invoke(cli.main, [str(a) for a in args], catch_exceptions=False)

    res = run("sync", ws_root, "--take", "SHAKE", "--fps", 15, "--mounts-from", "CAL")
    assert res.exit_code == 0, res.output
    assert "6 of 6 tracker mounts carried over from CAL" in res.output
    with Workspace.open(ws_root) as ws:
        assert ws.stage_record("sync", "CAL")["status"] == "done"  # synced first, on its own
        report = json.loads(ws.artifacts("sync", "SHAKE")["sync.json"].read_text())
        sync = SyncResult.load(ws.artifacts("sync", "SHAKE")["sync.npz"])
        cal = SyncResult.load(ws.artifacts("sync", "CAL")["sync.npz"])
    assert report["mounts_from"]["take"] == "CAL"
    for name in ("sim-a", "sim-b"):
        assert len(report["mounts_from"][name]["carried"]) == 6 and report["mounts_from"][name]["strapped_again"] == []
        assert report["common_offset"][name]["std_mm"] < 8.0, report["common_offset"]
        mine, theirs = sync.actor(name), cal.actor(name)
        for k, serial in enumerate(mine.serials):  # kept as solved on the calibration take
            j = theirs.serials.index(serial)
            assert np.array_equal(mine.mounts.rotations[k], theirs.mounts.rotations[j])
    studio = simulate_studio(scene.sequence, seed=1)
    errs = mount_errors(sync, studio)
    assert errs["rotation_deg"].max() < 0.8, errs
    alone = synchronise(read_columns(take), fps=15.0).report["common_offset"]
    assert all(alone[n]["std_mm"] > 2 * report["common_offset"][n]["std_mm"] for n in alone), alone
    assert not any("shared offset" in w for w in report.get("warnings", [])), report["warnings"]  # pinned by CAL
    # the trackers' lag behind the suits (a studio day's latencies) is averaged with the calibration's
    key = next(k for k in report["lags"] if k.startswith("source:"))
    lag = report["lags"][key]
    assert lag["carried_from"] == "CAL" and lag["latency_changed"] is False, lag
    assert lag["carried_lag_ms"] == cal.report["lags"][key]["lag_ms"]
    # their weighted mean, from the report's own figures (rounded to 0.1 us, and the two can lie that close)
    own_est, cal_est = (LagEstimate(lag[f"{w}_lag_ms"] * 1e6, lag[f"{w}_std_ms"] * 1e6, 1.0, 1) for w in ("own", "carried"))
    assert with_carried_lag(own_est, cal_est)[0].lag_ns * 1e-6 == pytest.approx(lag["lag_ms"], abs=1e-3), lag
    assert min(lag["own_lag_ms"], lag["carried_lag_ms"]) <= lag["lag_ms"] <= max(lag["own_lag_ms"], lag["carried_lag_ms"])
    clock = report["clocks"][key]
    assert abs(clock["offset_s"] - studio.trackers[0].clock.offset_s) < 1e-3, clock
    # a calibration 10 ms away: the latency changed; the take keeps its own lag, with a warning
    cal.report["lags"][key]["lag_ms"] += 10.0
    moved = synchronise(read_columns(take), fps=15.0, mounts_from=cal, mounts_from_take="CAL").report
    assert moved["lags"][key]["lag_ms"] == lag["own_lag_ms"] and moved["lags"][key]["latency_changed"] is True
    assert any("latency changed" in w for w in moved["warnings"]), moved["warnings"]
    # a calibration take that is not in the workspace, or the take itself: clear errors
    res = CliRunner().invoke(cli.main, ["sync", str(ws_root), "--take", "SHAKE", "--mounts-from", "NOPE"])
    assert res.exit_code != 0 and "no take 'NOPE'" in res.output
    res = CliRunner().invoke(cli.main, ["sync", str(ws_root), "--take", "SHAKE", "--mounts-from", "SHAKE"])
    assert res.exit_code != 0 and "cannot carry the mounts of itself" in res.output


@pytest.mark.slow
def test_the_suits_misalignments_bring_the_tracker_offsets_closer(recorded):
    """An inertial suit's limbs are off by tens of millimetres where its segments' orientations are
    misaligned (the simulated suit: 2 degrees RMS per segment). Solving those misalignments along
    each tracker's chain (sync/mount.py, SuitChain) keeps them out of the trackers' offsets, which
    the fit then holds the body to: on this take the offsets come out closer to the simulated ones."""
    from scipy.spatial.transform import Rotation

    from dualhuman_builder.body.mapping import MVN_SEGMENTS
    from dualhuman_builder.capture.log.reader import read_columns
    from dualhuman_builder.evaluation.fit import mount_errors
    from dualhuman_builder.fit.fuse import fuse_actor
    from dualhuman_builder.sim.studio import simulate_studio

    take, scene = recorded
    columns = read_columns(take)
    studio = simulate_studio(scene.sequence, seed=1)

    def offset_errors(sync):  # m, per tracker: where sync solves it, the suit's (misaligned) segment frame
        return mount_errors(sync, studio)["translation_mm"] / 1000

    with_chain = synchronise(columns, fps=15.0)
    without = synchronise(columns, fps=15.0, suit_chain=False)
    e_with, e_without = offset_errors(with_chain), offset_errors(without)
    assert e_with.shape == (12,) and e_with.mean() < 0.8 * e_without.mean(), (e_with, e_without)
    a = with_chain.actors[0]
    # every segment between the pelvis and a tracker (16 of MVN's 23), none solved without the chain
    assert len(a.mounts.chain_segments) == 16 and without.actors[0].mounts.chain_segments.size == 0
    assert np.degrees(np.linalg.norm(a.mounts.chain_misalignment_rad, axis=1)).max() < 10.0
    assert set(with_chain.report["mounts"]) == {"sim-a", "sim-b"} and "suit_misalignment" not in without.report
    arm = with_chain.report["suit_misalignment"]["sim-a"]["RightUpperArm"]
    assert len(arm["rotation_deg"]) == 3 and 0 < arm["std_deg"] < 5
    # where the root is known to: the trackers' shared offset (this handshake barely turns: ~14 mm)
    assert all(0 < c["std_mm"] < 30 for c in with_chain.report["common_offset"].values())
    # fusion turns each solved segment by -eps (RightUpperArm: untracked, on the right hand's chain)
    fused = fuse_actor(a, with_chain.times_s, 15.0)
    s = MVN_SEGMENTS.index("RightUpperArm")
    eps = a.mounts.chain_misalignment_rad[list(a.mounts.chain_segments).index(s)]
    ok = np.flatnonzero(a.suit_valid)[:5]
    yaw = Rotation.from_rotvec(np.outer(a.mounts.heading_rad[ok], [0.0, 1.0, 0.0]))
    expected = yaw * Rotation.from_quat(a.suit_rot[ok, s]) * Rotation.from_rotvec(-eps)
    got = Rotation.from_quat(fused.skeleton.orientations[ok, s])
    assert np.degrees((expected.inv() * got).magnitude()).max() < 1e-4 and np.degrees(np.linalg.norm(eps)) > 0.05


def _script_checks(monkeypatch, script) -> list:
    """Script what the fit's checks read: :meth:`CollisionTerm.penetration` runs for real, then
    ``script(n, keys, out)`` (``n``: 1 for the first check, ``keys`` its frames as ints, ``out`` the real
    reading) returns the entries of ``out`` to read instead (``max_depth_m``, ``share``), or None.
    Returns the list, filled as the fit runs, of each check's keys."""
    from dualhuman_builder.geometry import collision

    real = collision.CollisionTerm.penetration
    checks = []

    def read(self, va, vb, keys=None):
        out = real(self, va, vb, keys)
        checks.append([int(k) for k in keys])
        out.update(script(len(checks), checks[-1], out) or {})
        return out

    monkeypatch.setattr(collision.CollisionTerm, "penetration", read)
    return checks


def _overlapping_pair(T: int, dx: float = 0.05) -> list:
    """Fit inputs of two actors in the rest pose for ``T`` frames, pelvises ``dx`` metres apart
    along x (5 cm: the bodies overlap, so the collision pass runs), no trackers."""
    from dualhuman_builder.fit.fitter import ActorInput

    quat = np.tile([0.0, 0.0, 0.0, 1.0], (T, 23, 1))
    pelvis = np.tile([0.0, 0.95, 0.0], (T, 1))
    return [ActorInput(name, {}, quat, pelvis + [dx, 0, 0], np.ones(T, bool), np.zeros((T, 0, 3)), np.zeros((T, 0), bool),
                       np.zeros(0, np.int64), np.zeros((0, 3)), np.tile([[0.1, 0.1, 0.0], [-0.1, 0.1, 0.0]], (T, 1, 1)))
            for name, dx in (("a", 0.0), ("b", dx))]  # fmt: skip


@pytest.mark.parametrize("hands", [True, False])
def test_a_collision_pass_that_diverges_is_undone(model, monkeypatch, hands):
    """Two bodies on one spot: the collision passes run (the hands' first, when the fit may open
    them). If the loss turns non-finite, the line search steps to NaN corrections; the fitter undoes
    the pass and reports it, never returning NaN bodies or crashing."""
    from dualhuman_builder.geometry import collision

    T = 4
    inputs = _overlapping_pair(T)
    cfg = FitConfig(window=T, iterations=3, collision_iterations=3, collision_rounds=2, hand_opening=hands,
                    collision_hold_contacts=False)  # the contacts located at every evaluation (__call__)
    healthy = fit_actors(model, inputs, 15.0, cfg)
    assert healthy.summary["collision_frames"] == T and healthy.summary["collision_diverged"] == []
    real_call = collision.CollisionTerm.__call__

    def poisoned(self, va, vb, keys=None, points=None):
        r = real_call(self, va, vb, keys, points)
        r.loss = r.loss * float("nan")
        return r

    monkeypatch.setattr(collision.CollisionTerm, "__call__", poisoned)
    res = fit_actors(model, inputs, 15.0, cfg)
    # one window (a 4-frame window overlapping by 4 would only repeat it): its first pass is undone
    first = "the hands' collision pass" if hands else "collision round 1"
    assert res.summary["collision_diverged"] == [f"frames 0-3, {first}"]
    for track in res.sequence.actors:
        assert np.isfinite(np.asarray(track.pose)).all() and np.isfinite(np.asarray(track.transl)).all()
    # undone: the bodies are where the skeleton pass left them, still overlapping
    assert res.summary["max_penetration_after_mm"] == pytest.approx(res.summary["max_penetration_before_mm"], rel=1e-3)


def test_a_collision_pass_that_deepens_the_overlap_is_undone(model, monkeypatch):
    """A pass after which the window's deepest frame is deeper than the best before it is undone
    and reported; the next round starts again from the best answer, with the term weighted up.
    (As on a take whose trackers pull the bodies into each other; here the depth read after the
    first pass is read as 10 mm deeper than before it.)"""
    from dualhuman_builder.geometry import collision

    T = 2
    inputs = _overlapping_pair(T)
    # the rounds only (the hands' pass, which comes first, is undone by the same rule)
    cfg = FitConfig(window=T, overlap=0, iterations=3, collision_iterations=3, collision_rounds=2, hand_opening=False,
                    collision_hold_contacts=False)  # fmt: skip
    calls, seen = [], []

    def deeper_after_the_first_pass(n, keys, out):
        calls.append(float(out["max_depth_m"].max()))
        if n == 2:  # 1: after the skeleton pass, 2: after collision round 1, 3: round 2 (the summary reuses it)
            return {"max_depth_m": np.full_like(out["max_depth_m"], calls[0] + 0.010)}
        return None

    real_call = collision.CollisionTerm.__call__

    def watch(self, va, vb, keys=None, points=None):  # where each evaluation finds the bodies
        seen.append((len(calls), va.detach().clone()))
        return real_call(self, va, vb, keys, points)

    _script_checks(monkeypatch, deeper_after_the_first_pass)
    monkeypatch.setattr(collision.CollisionTerm, "__call__", watch)
    s = fit_actors(model, inputs, 15.0, cfg).summary
    assert s["collision_frames"] == T and s["collision_diverged"] == [] and len(calls) == 3
    assert s["collision_rounds_used"] == 2
    assert s["collision_worsened"] == [f"frames 0-1, collision round 1: {1000 * calls[0] + 10:.1f} mm after, "
                                       f"{1000 * calls[0]:.1f} mm before"]  # fmt: skip
    # round 2 started where round 1 started (its corrections undone), not where round 1 ended
    first_of_round = {n: v for n, v in reversed(seen)}
    assert torch.equal(first_of_round[1], first_of_round[2])
    assert calls[2] < calls[0]  # round 2 reduced the overlap, and its answer is kept
    assert s["max_penetration_after_mm"] == pytest.approx(1000 * calls[2], rel=1e-3)


@pytest.mark.parametrize("deep_m", [0.01, 0.0])
def test_frames_the_full_rounds_start_deep_are_weighted_a_step_ahead(model, monkeypatch, deep_m):
    """A frame the full rounds start with deeper than ``collision_deep_m`` has its collision term
    weighted one step (``collision_weight_step``) ahead of the others from round 1 on. Seen as the
    gradient of the fit's energy with respect to each frame's collision loss: the weight that frame
    pays. Here the checks after the skeleton pass and after round 1 read frame 0 as 15 mm deep and
    frame 1 as 5 mm."""
    from dualhuman_builder.geometry import collision

    T = 2
    cfg = FitConfig(window=T, overlap=0, iterations=3, collision_iterations=2, collision_rounds=2, hand_opening=False,
                    collision_hold_contacts=False, collision_deep_m=deep_m)  # fmt: skip
    real_call = collision.CollisionTerm.__call__
    weights = []
    # after the skeleton pass and after round 1 (so that round 2 runs)
    checks = _script_checks(monkeypatch, lambda n, keys, out: {"max_depth_m": np.array([0.015, 0.005])} if n <= 2 else None)

    def watch(self, va, vb, keys=None, points=None):
        r = real_call(self, va, vb, keys, points)
        if r.loss.requires_grad:
            r.loss.register_hook(lambda g, n=len(checks): weights.append((n, g.detach().clone())))
        return r

    monkeypatch.setattr(collision.CollisionTerm, "__call__", watch)
    s = fit_actors(model, _overlapping_pair(T, dx=0.02), 15.0, cfg).summary  # 2 cm: still in contact in round 2
    assert s["collision_rounds_used"] == 2 and s["collision_diverged"] == []
    w, step = cfg.collision_weight, cfg.collision_weight_step
    ahead = step if deep_m else 1.0
    by_round = {n: g for n, g in weights}  # n: checks before the evaluation (1: round 1, 2: round 2)
    assert set(by_round) == {1, 2}
    for n, g in weights:
        expected = torch.tensor([ahead, 1.0]) * w * step ** (n - 1)
        assert torch.allclose(g, expected, rtol=1e-6), (n, g, expected)


@pytest.mark.parametrize("hold", [True, False])
def test_a_round_moves_only_the_frames_left_over_a_tolerance_and_their_neighbours(model, monkeypatch, hold):
    """With ``collision_hold_settled`` a full round moves only the frames the pass before left over a
    tolerance and the two on either side (their smoothness terms read them); the others are held: no
    collision term is evaluated on them, the check after the round measures only the frames it moved,
    and they keep their corrections exactly. Here the checks read every frame 15 mm deep after the
    skeleton pass, only frame 6 of 8 over the tolerance after round 1, and nothing after round 2."""
    from dualhuman_builder.geometry import collision

    T = 8
    cfg = FitConfig(window=T, overlap=0, iterations=3, collision_iterations=2, collision_rounds=3, hand_opening=False,
                    collision_hold_contacts=False, collision_hold_settled=hold)  # fmt: skip
    real_call = collision.CollisionTerm.__call__
    evaluated, after = [], []  # after: the optimised tensors after each L-BFGS run

    def read(n, keys, out):
        depth = {1: 0.015, 2: 0.0}.get(n, 0.0)
        return {"max_depth_m": np.array([0.005 if (n == 2 and k == 6) else depth for k in keys]), "share": np.zeros(len(keys))}

    def watch(self, va, vb, keys=None, points=None):
        evaluated.append((len(checks), [int(k) for k in keys]))
        return real_call(self, va, vb, keys, points)

    real_step = torch.optim.LBFGS.step

    def step(self, closure):
        out = real_step(self, closure)
        after.append([p.detach().clone() for p in self.param_groups[0]["params"]])
        return out

    checks = _script_checks(monkeypatch, read)
    monkeypatch.setattr(collision.CollisionTerm, "__call__", watch)
    monkeypatch.setattr(torch.optim.LBFGS, "step", step)
    s = fit_actors(model, _overlapping_pair(T, dx=0.02), 15.0, cfg).summary
    assert s["collision_rounds_used"] == 2 and s["collision_diverged"] == [] and s["collision_worsened"] == []
    moved = [4, 5, 6, 7] if hold else list(range(T))
    assert checks[:2] == [list(range(T))] * 2 and checks[2] == moved
    round2 = {k for n, keys in evaluated if n == 2 for k in keys}
    assert round2 == set(moved)
    assert {k for n, keys in evaluated if n == 1 for k in keys} == set(range(T))
    assert len(after) == 3  # the skeleton pass, rounds 1 and 2: each actor's rotations and translations
    held = [k for k in range(T) if k not in moved]
    for r1, r2 in zip(after[1], after[2]):
        assert torch.equal(r1[held], r2[held])  # exactly where round 1 left them
        assert not torch.equal(r1[moved], r2[moved])


def test_a_window_left_within_the_tolerances_when_a_pass_is_undone_stops_there(model, monkeypatch):
    """The skeleton pass leaves shallow contacts only (1 mm, within the 2 mm tolerance), so the
    window gets its passes; the first leaves it deeper (read as 1.5 mm) and is undone. The best
    answer, the skeleton pass's, is then within the tolerances: the rounds stop there, with nothing
    to move (not on to a round of no frames, which the collision term rejects)."""
    T = 6
    cfg = FitConfig(window=T, overlap=0, iterations=3, collision_iterations=2, collision_rounds=3, hand_opening=False,
                    collision_hold_contacts=False, collision_hold_settled=True)  # fmt: skip
    checks = _script_checks(monkeypatch, lambda n, keys, out: {"max_depth_m": np.full(len(keys), 0.001 if n == 1 else 0.0015),
                                                                 "share": np.zeros(len(keys))})  # fmt: skip
    s = fit_actors(model, _overlapping_pair(T, dx=0.02), 15.0, cfg).summary
    assert len(checks) == 2 and checks[1] == list(range(T))  # the skeleton pass's check, round 1's
    assert s["collision_rounds_used"] == 1 and len(s["collision_worsened"]) == 1, s["collision_worsened"]
    assert s["max_penetration_after_mm"] == pytest.approx(1.0)  # the skeleton pass's answer, kept


@pytest.mark.parametrize("share_tolerance, rounds", [(0.0005, 2), (0.01, 1)])
def test_a_window_within_the_depth_tolerance_but_with_many_shallow_vertices_goes_round_again(
        model, monkeypatch, share_tolerance, rounds):  # fmt: skip
    """The rounds stop when the deepest frame is within 2 mm *and* no frame has more than
    ``collision_share_tolerance`` of the vertices inside the other body (a palm resting a millimetre
    deep: within the depth, over the issue's 0.1 % share). Here round 1 is read as leaving 1 mm and
    0.2 %, round 2 as 1 mm and none."""
    T = 2
    cfg = FitConfig(window=T, overlap=0, iterations=3, collision_iterations=3, collision_rounds=4, hand_opening=False,
                    collision_share_tolerance=share_tolerance, collision_hold_contacts=False)  # fmt: skip

    def shallow_but_wide(n, keys, out):
        if n in (2, 3):  # 1: after the skeleton pass, 2: after round 1, 3: after round 2
            return {"max_depth_m": np.full_like(out["max_depth_m"], 0.001),
                    "share": np.full_like(out["share"], 0.002 if n == 2 else 0.0)}  # fmt: skip
        return None

    _script_checks(monkeypatch, shallow_but_wide)
    s = fit_actors(model, _overlapping_pair(T), 15.0, cfg).summary
    assert s["collision_rounds_used"] == rounds and s["collision_worsened"] == []


def test_held_contacts_settle_a_window_and_a_stall_locates_its_deep_frames_exactly(model, monkeypatch):
    """By default each collision pass locates the contacts once and holds them (``linear_loss``), and
    the contacts are never located at every evaluation where the held rounds settle the window. When
    a held round stalls (here the held term is made to push nothing in frame 0, so round 1 leaves it
    as deep as it found it), the frames it left deeper than 75 % of the window's deepest start have
    their contacts located at every evaluation (``__call__``) from the next round on, the others stay
    held. A window the rounds leave unsettled (here: one round only) is fitted again from its skeleton
    pass with those frames and the ones left too deep exact, the rest held; where that is every frame
    (the held term pushing nothing anywhere) it gives the same bodies as a fit that never holds the
    contacts. Stalled rounds, exact frames and refitted windows are listed."""
    from dualhuman_builder.geometry import collision

    T = 2
    inputs = _overlapping_pair(T, dx=0.17)  # arms through the partner, 37 mm deep
    cfg = FitConfig(window=T, overlap=0, iterations=3, collision_iterations=6, hand_opening=False)
    calls = {"held": 0, "exact": 0}
    real_call, real_linear = collision.CollisionTerm.__call__, collision.CollisionTerm.linear_loss

    def count(kind, fn):
        def wrapped(self, *a, **k):
            calls[kind] += 1
            if kind == "exact":
                calls["exact rows"] = calls.get("exact rows", 0) + len(a[0])
            return fn(self, *a, **k)

        return wrapped

    monkeypatch.setattr(collision.CollisionTerm, "__call__", count("exact", real_call))
    monkeypatch.setattr(collision.CollisionTerm, "linear_loss", count("held", real_linear))
    held = fit_actors(model, inputs, 15.0, cfg)
    s = held.summary
    assert calls["held"] > 0 and calls["exact"] == 0
    assert s["collision_exact_frames"] == [] and s["collision_exact_windows"] == [] and s["collision_held_stalled"] == []
    assert s["max_penetration_before_mm"] > 20 and s["max_penetration_after_mm"] <= 1000 * cfg.collision_tolerance_m

    def nothing_in_frame_0(self, lin, points, device=None, dtype=torch.float32):
        loss = real_linear(self, lin, points, device, dtype)
        return loss * torch.tensor([0.0, 1.0]) if lin.B == 2 else loss  # (both frames held: rows 0, 1)

    monkeypatch.setattr(collision.CollisionTerm, "linear_loss", count("held", nothing_in_frame_0))
    calls.update(held=0, exact=0, **{"exact rows": 0})
    # feet free to slide: the frames share no term, so frame 1 cannot drag frame 0 out with it
    mixed = fit_actors(model, inputs, 15.0, dataclasses.replace(cfg, sigma_slide_m=1e3))
    s = mixed.summary
    assert s["collision_held_stalled"] == ["frames 0-1, collision round 1, held contacts"]
    assert s["collision_exact_frames"] == [0] and s["collision_exact_windows"] == []
    assert calls["exact"] > 0 and calls["exact rows"] == calls["exact"]  # frame 0 alone, located every time
    assert s["max_penetration_after_mm"] <= 1000 * cfg.collision_tolerance_m

    # one round only, frame 0's held term barely pushing: the round leaves frame 0 deep (without
    # stalling) and frame 1 settled, and the window is fitted again with frame 0 alone exact
    def weak_in_frame_0(self, lin, points, device=None, dtype=torch.float32):
        loss = real_linear(self, lin, points, device, dtype)
        return loss * torch.tensor([0.02, 1.0]) if lin.B == 2 else loss

    monkeypatch.setattr(collision.CollisionTerm, "linear_loss", count("held", weak_in_frame_0))
    calls.update(held=0, exact=0, **{"exact rows": 0})
    once = fit_actors(model, inputs, 15.0, dataclasses.replace(cfg, sigma_slide_m=1e3, collision_rounds=1))
    assert once.summary["collision_exact_windows"] == ["frames 0-1"] and once.summary["collision_exact_frames"] == []
    assert calls["exact"] > 0 and calls["exact rows"] == calls["exact"]

    def pushes_nothing(self, lin, points, device=None, dtype=torch.float32):
        return real_linear(self, lin, points, device, dtype) * 0.0

    monkeypatch.setattr(collision.CollisionTerm, "linear_loss", count("held", pushes_nothing))
    one = dataclasses.replace(cfg, collision_rounds=1)
    stalled = fit_actors(model, inputs, 15.0, one)
    s = stalled.summary
    assert s["collision_held_stalled"] == ["frames 0-1, collision round 1, held contacts"]
    assert s["collision_exact_frames"] == [0, 1] and s["collision_exact_windows"] == ["frames 0-1"]
    exact = fit_actors(model, inputs, 15.0, dataclasses.replace(one, collision_hold_contacts=False))
    assert exact.summary["collision_exact_windows"] == [] and exact.summary["collision_held_stalled"] == []
    for a, b in zip(stalled.sequence.actors, exact.sequence.actors):
        np.testing.assert_allclose(a.transl, b.transl, atol=1e-6)
        np.testing.assert_allclose(a.pose, b.pose, atol=1e-5)
    assert s["max_penetration_after_mm"] == pytest.approx(exact.summary["max_penetration_after_mm"], abs=1e-3)


@pytest.mark.parametrize("ratio", [2.0, 1e-9])
def test_held_rounds_that_settle_after_a_stall_with_the_shape_bent_are_fitted_again_exactly(model, monkeypatch, ratio):
    """Where the held rounds settle a window only after a stall, but with its skeleton energy more
    than ``collision_energy_ratio`` times the skeleton pass's, the window is fitted again the exact
    way and the lower-energy answer of the two is kept (listed in ``collision_energy_refits``). Here
    frame 0's held term pushes nothing, so round 1 stalls there and frame 0 goes exact; the window
    then settles at a ratio over 1e-9 but under 2."""
    import re

    from dualhuman_builder.geometry import collision

    T = 2
    inputs = _overlapping_pair(T, dx=0.17)
    cfg = FitConfig(window=T, overlap=0, iterations=3, collision_iterations=6, hand_opening=False, sigma_slide_m=1e3,
                    collision_energy_ratio=ratio)  # fmt: skip
    real_linear = collision.CollisionTerm.linear_loss

    def nothing_in_frame_0(self, lin, points, device=None, dtype=torch.float32):
        loss = real_linear(self, lin, points, device, dtype)
        return loss * torch.tensor([0.0, 1.0]) if lin.B == 2 else loss

    monkeypatch.setattr(collision.CollisionTerm, "linear_loss", nothing_in_frame_0)
    messages = []
    res = fit_actors(model, inputs, 15.0, cfg, progress=messages.append)
    s = res.summary
    assert s["collision_held_stalled"] == ["frames 0-1, collision round 1, held contacts"]
    assert s["max_penetration_after_mm"] <= 1000 * cfg.collision_tolerance_m
    if ratio == 2.0:
        assert s["collision_energy_refits"] == [] and s["collision_exact_windows"] == []
        return
    assert s["collision_exact_windows"] == ["frames 0-1"]
    [refit] = s["collision_energy_refits"]
    m = re.fullmatch(r"frames 0-1: skeleton energy ([0-9.]+)x the skeleton pass's held, ([0-9.]+)x exact; kept (held|exact)", refit)
    assert m, refit
    held, exact, kept = float(m[1]), float(m[2]), m[3]
    assert 0 < held < 2 and exact > 0
    if held != exact:  # (the ratios are printed to 2 decimals: equal ones do not say which was lower)
        assert kept == ("held" if held < exact else "exact")
    assert any("the held rounds settled with the skeleton energy" in x and "fitted again the exact way" in x for x in messages)


@pytest.mark.slow
def test_the_answers_depths_are_measured_once_and_are_its_own(model, monkeypatch):
    """The depths a fit reports after the collision term are those of the bodies it returns, frame by
    frame (measured again here on anny's own meshes), though the end of a segment measures only the
    frames no check measured at their final corrections (here: none)."""
    from dualhuman_builder.fit.problem import FitProblem
    from dualhuman_builder.geometry.collision import CollisionTerm
    from dualhuman_builder.fit.skeleton import torso_vertices

    T = 20
    inputs = _overlapping_pair(T, dx=0.17)  # arms through the partner
    cfg = FitConfig(window=8, overlap=2, segment_windows=0, iterations=3, collision_iterations=2, collision_rounds=1)
    measured = []
    real = FitProblem.depths

    def count(self, s0, s1, *a, **k):
        measured.append((s0, s1))
        return real(self, s0, s1, *a, **k)

    monkeypatch.setattr(FitProblem, "depths", count)
    res = fit_actors(model, inputs, 15.0, cfg, workers=1)
    got = res.frames["penetration depth (mm)/with collision term"]
    assert res.summary["collision_frames"] >= T and measured == []
    va, vb = (torch.as_tensor(np.array(a.vertices())) for a in res.sequence.actors)
    term = CollisionTerm(model.faces.cpu().numpy(), band_m=0.03, pad_m=0.01, guard_vertices=torso_vertices(model))
    fresh = term.penetration(va, vb)["max_depth_m"] * 1000
    assert fresh.max() > 0.1  # the bodies still touch somewhere, so the comparison means something
    np.testing.assert_allclose(got, fresh, atol=0.05)


def test_the_collision_passes_move_only_the_frames_around_the_contacts(model):
    """Actor b steps in to 10 cm from a for a few frames of a 40-frame take and back out: only those
    frames collide. The collision passes move the frames within ``collision_span_s`` of them (0.3 s:
    5 frames at 15 fps) and keep the rest of the window as the skeleton pass left it, bit for bit the
    bodies of a fit without the collision term; with ``collision_span_s=0`` the whole window moves."""
    from dualhuman_builder.fit.collision_rounds import span_rows
    from dualhuman_builder.fit.energy import join_contexts

    T, fps = 40, 15.0
    inputs = _overlapping_pair(T, dx=0.0)
    # 60 cm apart, 10 cm at frame 20 (the four skeleton iterations leave frames 19-21 in contact; more would
    # smooth the step away: nothing but the trackers, here none, holds the pelvis to its data)
    x = 0.6 - 0.5 * np.exp(-(((np.arange(T) - 20) / 3.0) ** 2))
    inputs[1].pelvis = inputs[1].pelvis + np.stack([x, np.zeros(T), np.zeros(T)], 1)
    cfg = FitConfig(window=T, iterations=4, collision_iterations=3, collision_rounds=1, hand_opening=False)
    off = fit_actors(model, inputs, fps, dataclasses.replace(cfg, collision=False))
    on = fit_actors(model, inputs, fps, cfg)
    hit = np.flatnonzero(on.frames["penetration depth (mm)/without collision term"] > 0)
    assert len(hit) and hit[0] > 8 and hit[-1] < T - 9  # a few frames in the middle collide
    r0, r1 = span_rows(hit, T, cfg, fps)
    assert (r0, r1) == (hit[0] - 5, hit[-1] + 6)
    outside = np.r_[0:r0, r1:T]
    for a, b in zip(on.sequence.actors, off.sequence.actors):
        assert np.array_equal(np.asarray(a.pose)[outside], np.asarray(b.pose)[outside])
        assert np.array_equal(np.asarray(a.transl)[outside], np.asarray(b.transl)[outside])
        assert np.abs(np.asarray(a.transl)[hit] - np.asarray(b.transl)[hit]).max() > 1e-4  # pushed apart there
    assert on.summary["max_penetration_after_mm"] < on.summary["max_penetration_before_mm"]
    whole = fit_actors(model, inputs, fps, dataclasses.replace(cfg, collision_span_s=0.0))
    moved = [np.abs(np.asarray(a.transl)[outside] - np.asarray(b.transl)[outside]).max()
             for a, b in zip(whole.sequence.actors, off.sequence.actors)]  # fmt: skip
    assert max(moved) > 0
    # the span's rows at the window's edges, and the contexts it reads around it
    assert span_rows(np.array([1, 2]), 48, cfg, fps) == (0, 8) and span_rows(np.array([46]), 48, cfg, fps) == (41, 48)
    assert span_rows(np.array([], np.int64), 48, cfg, fps) == (0, 48)
    ctx = tuple(torch.full((n, 3), float(v)) for n, v in ((1, 1), (1, 1), (1, 1)))
    rows = tuple(torch.arange(3.0)[:, None].repeat(1, 3) + 10 for _ in range(3))
    assert join_contexts(ctx, rows, last=True)[0][:, 0].tolist() == [11.0, 12.0]
    assert join_contexts(rows, ctx, last=False)[0][:, 0].tolist() == [10.0, 11.0]
    assert join_contexts(None, ctx, last=True)[0].shape == (1, 3) and join_contexts(None, None, last=False) is None


def test_stuck_frames_restart_from_their_neighbours():
    """A run of stuck frames inside the window is set to the straight line between the frames around
    it (every parameter tensor), one at the window's edge to its one neighbour; frames outside the
    runs are untouched; a window stuck everywhere has nothing to start from."""
    from dualhuman_builder.fit.collision_rounds import restart_from_neighbours

    W = 10
    delta = torch.arange(W, dtype=torch.float32)[:, None, None].repeat(1, 23, 3) ** 2  # (W, 23, 3)
    opening = torch.arange(W, dtype=torch.float32)[:, None].repeat(1, 4) * -1.0  # (W, 4)
    params = [delta.clone(), opening.clone()]
    stuck = np.zeros(W, bool)
    stuck[[0, 1, 4, 5, 6]] = True
    assert restart_from_neighbours(params, stuck)
    d = params[0][:, 0, 0]
    # frames 4-6 between frame 3 (9) and frame 7 (49): 19, 29, 39; frames 0-1 copy frame 2 (4)
    np.testing.assert_allclose(d.numpy(), [4, 4, 4, 9, 19, 29, 39, 49, 64, 81], rtol=1e-6)
    np.testing.assert_allclose(params[1][:, 2].numpy(), [-2, -2, -2, -3, -4, -5, -6, -7, -8, -9], rtol=1e-6)
    assert torch.equal(params[0][:, 5], params[0][:, 0])  # every element of a frame moves alike
    frozen = [delta.clone()]
    assert not restart_from_neighbours(frozen, np.ones(W, bool)) and torch.equal(frozen[0], delta)


@pytest.mark.slow
def test_a_foot_in_stance_stands_on_the_floor(model):
    """A standing body whose soles float 8 mm above the floor (the trackers' offsets can leave one
    so: nothing else holds it down) is put on the floor by the stance contact term: the lowest sole
    vertex of each foot ends at height 0. Without the term it stays where it started; a body sunk
    into the floor comes out with or without it (the floor term), onto it only with it."""
    from dualhuman_builder.fit.fitter import ActorInput
    from dualhuman_builder.fit.skeleton import sole_vertices

    T = 6
    soles = sole_vertices(model)
    from scipy.spatial.transform import Rotation

    rest_frames = BodyRig(model, {}).seg_frame.cpu().numpy()  # segment orientations of anny's rest pose
    quat = np.tile(Rotation.from_matrix(rest_frames).as_quat(), (T, 1, 1))
    ankles = np.tile([[0.1, 0.05, 0.0], [-0.1, 0.05, 0.0]], (T, 1, 1))  # still and low: in stance

    def lowest(height, sigma):
        inp = ActorInput("a", {}, quat, np.tile([0.0, height, 0.0], (T, 1)), np.ones(T, bool), np.zeros((T, 0, 3)),
                         np.zeros((T, 0), bool), np.zeros(0, np.int64), np.zeros((0, 3)), ankles)  # fmt: skip
        v = fit_actors(model, [inp], 15.0, FitConfig(sigma_contact_m=sigma)).sequence[0].vertices()
        return np.stack([v[:, soles[s], 1].min(1) for s in ("L", "R")], 1)  # (T, 2) m

    rest = lowest(0.95, 0.0)
    assert np.ptp(rest) < 1e-4  # both feet flat at one height: nothing moved the body
    floor = 0.95 - float(rest.mean())  # pelvis height with the soles on the floor
    floating = lowest(floor + 0.008, 0.0)
    assert np.allclose(floating, 0.008, atol=3e-4)
    assert np.abs(lowest(floor + 0.008, 0.002)).max() < 5e-4
    # sunk 5 mm: the floor term lifts it out, but with nothing holding it above the floor (no trackers
    # here) only the contact term puts it back on the floor
    assert lowest(floor - 0.005, 0.0).min() > -1e-3 and np.abs(lowest(floor - 0.005, 0.002)).max() < 5e-4


def test_the_fit_runs_on_the_configured_torch_threads_and_restores_the_callers(model):
    """torch's CPU threads are ``FitConfig.torch_threads`` during the fit (1 by default: with more,
    fits of the same inputs differed between runs), and the caller's setting afterwards, also when
    the fit fails; 0 leaves the caller's setting."""
    import dataclasses

    import torch

    from dualhuman_builder.fit.fitter import FitConfig, FitError, fit_actors

    seen = []
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        inputs = _overlapping_pair(4, dx=1.0)  # far apart: the skeleton pass only
        for threads, expect in ((1, 1), (0, 2)):
            fit_actors(model, inputs, 15.0, FitConfig(window=4, iterations=2, torch_threads=threads),
                       progress=lambda _m: seen.append(torch.get_num_threads()))  # fmt: skip
            assert seen and set(seen) == {expect} and torch.get_num_threads() == 2
            seen.clear()
        with pytest.raises(FitError):
            fit_actors(model, [inputs[0], dataclasses.replace(inputs[1], seg_rot=inputs[1].seg_rot[:2])], 15.0,
                       FitConfig(torch_threads=1))  # fmt: skip
        assert torch.get_num_threads() == 2
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("window,overlap,per", [(48, 4, 2), (4, 1, 1), (6, 2, 3), (48, 4, 0)])
def test_the_take_is_cut_into_windows_and_segments_that_cover_it(window, overlap, per):
    """Windows cover every frame, each starting inside the one before and none only repeating the
    one before's last frames; groups of ``segment_windows`` windows form segments (0: one), and a
    segment's first window starts ``overlap`` frames early, so consecutive segments share ``2
    overlap`` frames."""
    from dualhuman_builder.fit.fitter import layout

    cfg = FitConfig(window=window, overlap=overlap, segment_windows=per)
    for T in (2, 5, 47, 48, 49, 92, 93, 180, 181, 500):
        segments = layout(T, cfg)
        wins = [w for seg in segments for w in seg]
        assert [w[0] for w in wins] == list(range(len(wins)))
        assert wins[0][1] == 0 and wins[-1][2] == T
        assert all(s1 - s0 <= window + overlap for _, s0, s1 in wins)
        for (_, a0, a1), (_, b0, b1) in zip(wins, wins[1:]):
            assert a0 < b0 <= a1 and b1 > a1
        if per == 0:
            assert len(segments) == 1
            continue
        assert all(1 <= len(seg) <= per for seg in segments) and len(segments) == -(-len(wins) // per)
        for prev, seg in zip(segments, segments[1:]):
            shared = prev[-1][2] - seg[0][1]
            assert shared == min(2 * overlap, prev[-1][2] - prev[-1][1]), (T, prev, seg)


def test_segments_are_cross_faded_over_the_frames_they_share():
    from dualhuman_builder.fit.layout import SegmentAnswer, cross_fade

    def part(start, n, value):
        full = lambda *s: np.full((n,) + s, value, np.float32)  # noqa: E731
        return SegmentAnswer(start, [full(23, 3)], [full(3)], [full(4)], np.full(n, value), np.full(n, value))

    j = cross_fade([part(0, 6, 0.0), part(2, 6, 1.0), part(7, 3, 3.0)], 10)
    want = np.array([0, 0, 0.2, 0.4, 0.6, 0.8, 1, 1 + 2 / 2, 3, 3])
    for key in ("delta", "dtransl", "opening"):
        assert j[key][0].shape[0] == 10 and j[key][0].dtype == np.float32
        np.testing.assert_allclose(j[key][0].reshape(10, -1), np.repeat(want[:, None], j[key][0][0].size, 1), atol=1e-6)
    np.testing.assert_array_equal(j["pen_before"], [0, 0, 1, 1, 1, 1, 1, 3, 3, 3])  # the later segment's


@pytest.mark.slow
def test_a_seam_whose_cross_fade_passes_through_the_partner_is_fitted_again(model):
    """Two segments that leave actor b on opposite sides of a (30 cm to its left in one, 50 cm to
    its right in the other): the blend of their shared frames takes b through a. That seam is
    fitted again from the blend, over the shared frames and ``overlap`` more on each side, with the
    frames around it fixed: afterwards no frame is deeper than the tolerance, and the frames outside
    that window are untouched."""
    from dualhuman_builder.fit.layout import SegmentAnswer, cross_fade
    from dualhuman_builder.fit.seams import apply_seams, fit_seam
    from dualhuman_builder.fit.segment import SegmentFitter

    T = 12
    cfg = FitConfig(window=4, overlap=1, iterations=3, collision_iterations=4, hand_opening=False)
    fitter = SegmentFitter(model, _overlapping_pair(T, dx=0.5), 15.0, cfg)

    def part(start, n, bx):
        z = lambda *s: np.zeros((n,) + s, np.float32)  # noqa: E731
        bt = z(3)
        bt[:, 0] = bx
        return SegmentAnswer(start, [z(23, 3), z(23, 3)], [z(3), bt], [z(4), z(4)], np.zeros(n), np.zeros(n))

    def depths(j):
        vs = [a.pose(*(torch.as_tensor(j[key][k]) for key in ("delta", "dtransl")), slice(0, T), True,
                     torch.as_tensor(j["opening"][k]))[1].vertices for k, a in enumerate(fitter.acts)]  # fmt: skip
        return fitter.collide.penetration(vs[0], vs[1])["max_depth_m"]

    parts = [part(0, 7, 0.0), part(5, 7, -0.8)]  # shared: frames 5, 6
    j = cross_fade(parts, T)
    before = {key: [x.copy() for x in j[key]] for key in ("delta", "dtransl", "opening")}
    d = depths(j)
    assert d[[0, 1, 2, 3, 4, 7, 8, 9, 10, 11]].max() == 0 and d[5:7].max() > 0.02  # the blend: b through a
    said = []
    seam = fit_seam(fitter, parts[0], parts[1], said.append)
    assert (seam.b0, seam.e) == (5, 7) and seam.depth.max() > 0.02 and seam.fixed is not None
    assert apply_seams(j, [seam]) == ["frames 4-7"]
    np.testing.assert_array_equal(j["pen_after"][4:8], seam.fixed.pen_after)
    assert any("seam frames 5-6" in m and "mm deep after the cross-fade" in m for m in said), said
    assert depths(j).max() <= cfg.collision_tolerance_m
    for key in before:
        for x, y in zip(before[key], j[key]):
            np.testing.assert_array_equal(x[:4], y[:4])
            np.testing.assert_array_equal(x[8:], y[8:])
            assert not np.array_equal(x[4:8], y[4:8]) or key == "opening"


def test_fit_workers_follow_cpus_segments_memory_and_the_device():
    from dualhuman_builder.fit.fitter import WORKER_BYTES, fit_workers

    cfg = FitConfig()
    plenty = 64 * WORKER_BYTES
    assert fit_workers(5, cfg, cpus=2, available_bytes=plenty) == 2
    assert fit_workers(5, cfg, cpus=16, available_bytes=plenty) == 5
    assert fit_workers(1, cfg, cpus=16, available_bytes=plenty) == 1
    assert fit_workers(5, cfg, cpus=16, available_bytes=3 * WORKER_BYTES + 1) == 3
    assert fit_workers(5, cfg, cpus=16, available_bytes=WORKER_BYTES // 2) == 1
    assert fit_workers(5, FitConfig(device="cuda"), cpus=16, available_bytes=plenty) == 1


def test_the_collision_term_shares_the_cpus_among_the_fits_processes(model):
    """Each of a fit's processes gives its collision term the CPUs shared out among them (at least one,
    at most eight): two processes on two CPUs run one query thread each, not two that wait on each
    other."""
    from dualhuman_builder.fit.fitter import collision_threads
    from dualhuman_builder.fit.segment import SegmentFitter

    assert [collision_threads(p, cpus=2) for p in (1, 2, 3)] == [2, 1, 1]
    assert collision_threads(1, cpus=16) == 8 and collision_threads(4, cpus=16) == 4
    cfg = FitConfig(window=4)
    assert SegmentFitter(model, _overlapping_pair(4), 15.0, cfg, threads=1).collide.threads == 1


def test_both_actors_skeleton_energy_at_once_is_the_sum_of_each_alone(model):
    """The skeleton terms of both actors are evaluated as one stack (:class:`ActorStack`, trackers padded to
    the most either has): energy and gradient equal the sum of each actor evaluated alone, here with
    six trackers on one actor and three (one of them missing every third frame) on the other, with
    fixed context frames on both sides."""
    from dualhuman_builder.fit.actors import ActorStack
    from dualhuman_builder.fit.energy import context_of, skeleton_energy, stack_contexts
    from dualhuman_builder.fit.segment import SegmentFitter

    T = 12
    inputs = _overlapping_pair(T, dx=0.6)
    rng = np.random.default_rng(0)
    for inp, K in zip(inputs, (6, 3)):
        inp.trk_pos = inp.pelvis[:, None, :] + rng.normal(0, 0.3, (T, K, 3))
        inp.trk_valid = np.ones((T, K), bool)
        inp.trk_segment = np.arange(K) * 3
        inp.trk_offset = rng.normal(0, 0.05, (K, 3))
    inputs[1].trk_valid[::3, 1] = False
    cfg = FitConfig()
    fitter = SegmentFitter(model, inputs, 15.0, cfg)
    assert fitter.stack.K == 6
    torch.manual_seed(0)
    sl, n = slice(3, 9), 6
    ps = [[(0.1 * torch.randn(n, *shape)).requires_grad_() for shape in ((23, 3), (3,), (4,))] for _ in range(2)]
    with torch.no_grad():
        ctx, after = ([context_of(a, 0.1 * torch.randn(2, 23, 3), torch.zeros(2, 3), torch.full((2, 4), 0.2), s)
                       for a in fitter.acts] for s in (slice(1, 3), slice(9, 11)))  # fmt: skip
    both, rot = skeleton_energy(fitter.stack, *(torch.stack([p[j] for p in ps]) for j in range(3)), sl, stack_contexts(ctx), cfg, 15.0,
                        stack_contexts(after))  # fmt: skip
    alone = [skeleton_energy(ActorStack([a]), *(p[j][None] for j in range(3)), sl, stack_contexts([c]), cfg, 15.0, stack_contexts([f]))[0]
             for a, p, c, f in zip(fitter.acts, ps, ctx, after)]  # fmt: skip
    assert rot.shape == (2, n, 23, 3, 3) and alone[0] > 0 and alone[1] > 0
    assert float(both.detach()) == pytest.approx(float((alone[0] + alone[1]).detach()), rel=1e-5)
    flat = [x for p in ps for x in p]
    for x, y in zip(torch.autograd.grad(both, flat), torch.autograd.grad(alone[0] + alone[1], flat)):
        assert torch.allclose(x, y, rtol=1e-4, atol=1e-3 * float(y.abs().max()))


@pytest.mark.slow
def test_segments_fitted_in_worker_processes_give_the_same_bodies(model, monkeypatch):
    """The same take fitted in this process alone, by one worker process (this one made to leave it
    every segment), and with a worker that cannot start (this process then fits every segment
    itself and says why): the same bodies to the bit, collision passes included, and every window's
    progress line arrives."""
    import sys

    from dualhuman_builder.fit import workers as fit_workers_module

    T = 10
    inputs = _overlapping_pair(T, dx=0.1)
    cfg = FitConfig(window=4, overlap=1, segment_windows=1, iterations=3, collision_iterations=3, collision_rounds=2,
                    hand_opening=False)  # fmt: skip
    runs, said = {}, {}
    for name, workers in (("here", 1), ("workers", 2), ("broken", 2)):
        said[name] = []
        with monkeypatch.context() as mp:
            mp.setattr(fit_workers_module, "HERE_TOO", name == "here")
            if name == "broken":
                mp.setattr(sys, "executable", "/bin/false")
            runs[name] = fit_actors(model, inputs, 15.0, cfg, progress=said[name].append, workers=workers)
    s = runs["here"].summary
    assert s["segments"] == 3 and s["processes"] == 1 and s["collision_frames"] > 0
    assert runs["workers"].summary["processes"] == 2 and runs["broken"].summary["processes"] == 2
    assert runs["workers"].summary["worker_peak_rss_mb"] > 100  # the worker fitted (it reported its memory)
    assert runs["broken"].summary["worker_peak_rss_mb"] == 0
    for name in ("workers", "broken"):
        for a, b in zip(runs["here"].sequence.actors, runs[name].sequence.actors):
            np.testing.assert_array_equal(a.pose, b.pose)
            np.testing.assert_array_equal(a.transl, b.transl)
        for key in ("collision_frames", "max_penetration_before_mm", "max_penetration_after_mm", "seams_fitted_again"):
            assert runs[name].summary[key] == s[key], key
        assert sorted(m for m in said[name] if m.startswith("window")) == sorted(m for m in said["here"] if m.startswith("window"))
    assert any(m.startswith("WARNING: fit worker 1 exited with status 1") for m in said["broken"]), said["broken"]
    assert [m for m in said["broken"] if "its worker failed" in m] == [f"fitting segment {i} in this process (its worker failed)" for i in (1, 2, 3)]


def test_an_unmeasured_segment_pulls_its_bone_only_weakly(model):
    """A segment no sensor measured (an upper-body recording's legs, ``ActorInput.segment_weight`` 0)
    keeps only :data:`~dualhuman_builder.fit.actors.UNMEASURED_WEIGHT` of the orientation term: turning
    that bone away from the suit's pose costs that share of what turning a measured bone costs."""
    from dualhuman_builder.body.mapping import MVN_SEGMENTS
    from dualhuman_builder.fit.actors import UNMEASURED_WEIGHT
    from dualhuman_builder.fit.energy import skeleton_energy
    from dualhuman_builder.fit.inputs import segment_weights
    from dualhuman_builder.fit.segment import SegmentFitter

    T, sl = 6, slice(0, 6)
    inputs = _overlapping_pair(T, dx=0.6)
    inputs[0].segment_weight = segment_weights(["RightUpperLeg"])
    # only the orientation term: no smoothness, floor, stance or sliding terms to see the leg move
    fitter = SegmentFitter(model, inputs, 15.0, FitConfig(sigma_accel_m_s2=1e9, sigma_floor_m=1e9, sigma_contact_m=0.0,
                                                          sigma_slide_m=1e9))  # fmt: skip
    leg, arm = MVN_SEGMENTS.index("RightUpperLeg"), MVN_SEGMENTS.index("RightUpperArm")
    zeros = torch.zeros(2, T, 23, 3)

    def cost(actor: int, seg: int) -> float:
        delta = zeros.clone()
        delta[actor, :, seg, 0] = 0.2
        rest = skeleton_energy(fitter.stack, zeros, torch.zeros(2, T, 3), torch.zeros(2, T, 4), sl, None, fitter.cfg, 15.0)[0]
        turned = skeleton_energy(fitter.stack, delta, torch.zeros(2, T, 3), torch.zeros(2, T, 4), sl, None, fitter.cfg, 15.0)[0]
        return float(turned - rest)

    assert cost(0, leg) == pytest.approx(UNMEASURED_WEIGHT * cost(0, arm), rel=0.05)
    assert cost(1, leg) == pytest.approx(cost(1, arm), rel=0.05)  # the other actor's legs were measured

"""Ground-truth scenes: the quality contract for every type and several seeds, the ground-truth
distances against libigl, save/load, determinism, and the pieces the generator is built from."""

from __future__ import annotations

import numpy as np
import pytest

from dualhuman_builder.sim.scenes import (CONTACT_THRESHOLD, MAX_PENETRATION_M, MAX_STANCE_SLIDE_M, SCENE_TYPES, Scene,
                                          SceneParams, contract_failures, make_scene)  # fmt: skip

FPS = 15.0  # small, so the whole contract runs in a few minutes; the generator is fps-independent
_CACHE: dict = {}


def scene_of(kind: str, seed: int) -> Scene:
    if (kind, seed) not in _CACHE:
        _CACHE[(kind, seed)] = make_scene(SceneParams(type=kind, seed=seed, fps=FPS))
    return _CACHE[(kind, seed)]


def _closed_mesh(model):
    from dualhuman_builder.body.topology import collision_faces

    faces = model.faces.cpu().numpy()
    return faces[collision_faces(faces, model.num_vertices)]


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("kind", SCENE_TYPES)
def test_scene_quality_contract(kind, seed, body_model):
    from dualhuman_builder.sim.quality import foot_sliding, joint_limit_violations

    sc = scene_of(kind, seed)
    seq = sc.sequence
    assert seq.num_frames == int(round(sc.params.fps * sc.times[-1])) + 1
    # the two actors differ in shape, and stand on the floor
    assert not np.allclose(seq.actors[0].shape, seq.actors[1].shape)
    for track in seq.actors:
        assert abs(float(track.vertices()[0][:, 1].min())) < 0.02
    # interpenetration, from the stored ground-truth distances (negative = inside the partner)
    d = [np.nan_to_num(x.astype(np.float32), nan=np.inf) for x in sc.distances]
    assert -min(d[0].min(), d[1].min()) <= MAX_PENETRATION_M
    # planted feet do not slide, and some frames are stance frames
    for i, track in enumerate(seq.actors):
        assert any(m.sum() > 3 for m in sc.stance[i].values())
        assert foot_sliding(track, sc.stance[i]) <= MAX_STANCE_SLIDE_M
    # contact on every frame of every contact phase, none long before the first
    mask = sc.contact_phase_mask()
    assert mask.any()
    gap = np.minimum(d[0].min(1), d[1].min(1))
    assert (gap[mask] < CONTACT_THRESHOLD).all(), f"frames without contact: {np.flatnonzero(mask & (gap >= CONTACT_THRESHOLD))}"
    assert gap[0] > CONTACT_THRESHOLD
    # joints within anatomical limits
    for track in seq.actors:
        assert joint_limit_violations(track) == {}
    assert contract_failures(sc.stats) == []
    # seeds 0 and 1 meet it on their own draw, unrepaired: the scenes kept recordings were made from
    assert sc.stats["draws"] == 1 and sc.stats["repaired"] is False


@pytest.mark.slow
def test_the_calibration_scene_turns_every_tracked_segment_both_ways(body_model):
    """The calibration motion of a studio day (``calibration``, not an interaction): the actors never
    touch, the contract holds, and every segment a tracker is strapped to turns about the vertical
    (the spin: tells an offset from the suit's drift) and every one but the flat-footed feet tilts
    away from it (tells a mounting rotation from the suit's heading)."""
    from scipy.spatial.transform import Rotation

    from dualhuman_builder.body.mapping import MVN_SEGMENTS
    from dualhuman_builder.sim.groundtruth import segment_kinematics
    from dualhuman_builder.sim.scenes import ALL_TYPES, CALIBRATION_TYPE

    assert CALIBRATION_TYPE in ALL_TYPES and CALIBRATION_TYPE not in SCENE_TYPES
    sc = scene_of(CALIBRATION_TYPE, 0)
    assert contract_failures(sc.stats) == [] and sc.contact_phases == []
    d = [np.nan_to_num(x.astype(np.float32), nan=np.inf) for x in sc.distances]
    assert min(d[0].min(), d[1].min()) > 0.5  # far apart throughout
    for track in sc.sequence.actors:
        q = np.asarray(segment_kinematics(track, model=body_model).orientations)
        for seg in ("Pelvis", "Head", "LeftHand", "RightHand", "LeftFoot", "RightFoot"):
            rel = Rotation.from_quat(q[:, MVN_SEGMENTS.index(seg)]) * Rotation.from_quat(q[0, MVN_SEGMENTS.index(seg)]).inv()
            yaw = np.unwrap(rel.as_euler("YXZ")[:, 0])
            up = rel.apply([0.0, 1.0, 0.0])  # where the segment's world-vertical went: its tilt
            tilt = np.degrees(np.arccos(np.clip(up[:, 1], -1, 1)))
            assert np.degrees(np.ptp(yaw)) > 300, seg  # one full spin
            if not seg.endswith("Foot"):  # the performer keeps soles flat: feet only turn
                assert tilt.max() > 15.0, (seg, tilt.max())
    with pytest.raises(ValueError, match="at least 1.2 m"):
        make_scene(SceneParams(type=CALIBRATION_TYPE, seed=0, fps=FPS, approach_distance=0.8))


def test_distances_agree_with_libigl(body_model):
    """The stored signed distances (warp BVH, float16) against igl.signed_distance on the frame
    where the bodies are closest."""
    import igl

    sc = scene_of("handshake", 0)
    gap = np.stack([np.nan_to_num(x.astype(np.float32), nan=np.inf) for x in sc.distances]).min(axis=(0, 2))
    f = int(np.argmin(gap))
    va, vb = (a.vertices()[f].astype(np.float64) for a in sc.sequence.actors)
    faces = _closed_mesh(body_model).astype(np.int64)
    stored = sc.distances[0][f].astype(np.float64)
    near = np.flatnonzero(np.isfinite(stored))
    assert len(near) > 20
    ref = igl.signed_distance(va[near], vb, faces, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0]
    np.testing.assert_allclose(stored[near], ref, atol=1e-4)  # float16 storage over a 5 cm band
    # beyond the band is NaN, and really farther than it
    far = np.flatnonzero(~np.isfinite(stored))[::500]
    ref_far = igl.signed_distance(va[far], vb, faces, sign_type=igl.SIGNED_DISTANCE_TYPE_PSEUDONORMAL)[0]
    assert (np.abs(ref_far) > 0.049).all()
    # the per-vertex contact labels are the distances below the threshold
    labels = sc.contact_labels()
    assert labels[0][f].sum() == (stored < CONTACT_THRESHOLD).sum() > 0


def test_save_load_round_trip_and_bad_files(tmp_path):
    from dualhuman_builder.errors import FormatError

    sc = scene_of("high_five", 0)
    path = sc.save(tmp_path / "s.npz")
    back = Scene.load(path)
    assert back.params == sc.params
    np.testing.assert_array_equal(back.sequence.actors[1].pose, sc.sequence.actors[1].pose)
    np.testing.assert_array_equal(back.distances[0], sc.distances[0])
    assert back.phases == sc.phases and back.contact_phases == sc.contact_phases
    assert back.stats["max_penetration_m"] == sc.stats["max_penetration_m"]
    (tmp_path / "junk.npz").write_bytes(b"not a zip")
    with pytest.raises(FormatError):
        Scene.load(tmp_path / "junk.npz")
    with pytest.raises(FormatError):
        Scene.load(sc.sequence.save(tmp_path / "seq.npz"))  # an InteractionSequence is not a Scene


@pytest.mark.slow
def test_deterministic_and_parameters_act(body_model):
    a = scene_of("high_five", 0)
    b = make_scene(SceneParams(type="high_five", seed=0, fps=FPS))
    np.testing.assert_array_equal(a.sequence.actors[0].pose, b.sequence.actors[0].pose)
    # tempo 2 halves the natural length; a longer duration pads; too short is refused
    fast = make_scene(SceneParams(type="high_five", seed=0, fps=FPS, tempo=2.0, duration=None))
    assert abs(fast.sequence.num_frames - a.sequence.num_frames / 2) <= 1
    assert fast.contact_phases[0][0] == pytest.approx(a.contact_phases[0][0] / 2)
    with pytest.raises(ValueError, match="too short"):
        make_scene(SceneParams(type="high_five", seed=0, fps=FPS, duration=1.0))
    with pytest.raises(ValueError, match="unknown scene type"):
        SceneParams(type="waltz")
    # a wider approach distance: the actors start farther apart
    wide = make_scene(SceneParams(type="high_five", seed=0, fps=FPS, approach_distance=2.6))
    start = lambda s: np.linalg.norm(s.sequence.actors[0].transl[0] - s.sequence.actors[1].transl[0])  # noqa: E731
    assert start(wide) == pytest.approx(2.6, abs=0.05) and start(wide) > start(a) + 0.3


def test_skeleton_fk_matches_the_body_model(body_model):
    """The generator's fast forward kinematics against anny's own bone heads, on a scene's poses."""
    import roma
    import torch

    from dualhuman_builder.sim.skeleton import Skeleton

    track = scene_of("high_five", 0).sequence.actors[0]
    sk = Skeleton.from_model(body_model, np.array(track.shape))
    local = roma.rotvec_to_rotmat(torch.tensor(np.array(track.pose), dtype=torch.float64)).numpy()
    assert sk.check_against_model(body_model, local[::10], np.array(track.transl)[::10]) < 1e-4
    heads, _ = sk.fk(local, np.array(track.transl))
    np.testing.assert_allclose(heads, track.bone_heads(), atol=1e-4)


def test_two_bone_ik_reaches_bends_towards_the_pole_and_clamps(body_model):
    from dualhuman_builder.sim.ik import LimbChain
    from dualhuman_builder.sim.skeleton import Skeleton

    sk = Skeleton.from_model(body_model, np.array(scene_of("high_five", 0).sequence.actors[0].shape))
    arm = LimbChain(sk, "upperarm01.R", "lowerarm01.R", "wrist.R")
    local, transl = sk.identity(2), np.zeros((2, 3))
    heads, _ = sk.fk(local, transl)
    shoulder = heads[0, arm.iu]
    # reachable: the wrist lands on the target, the elbow bends towards the pole (backwards, -Z)
    target = shoulder + np.array([-0.15, -0.25, 0.30])
    pole = np.tile([0.0, -1.0, -1.0], (2, 1))
    reached, _ = arm.solve(local, transl, np.stack([target, target]), pole)
    heads, _ = sk.fk(local, transl)
    np.testing.assert_allclose(heads[:, arm.ie], np.stack([target, target]), atol=1e-6)
    np.testing.assert_allclose(reached, heads[:, arm.ie], atol=1e-9)
    elbow = heads[0, arm.il]
    mid = shoulder + 0.5 * (target - shoulder)
    assert (elbow - mid) @ np.array([0.0, -1.0, -1.0]) > 0.02
    # bone lengths are kept
    assert np.linalg.norm(elbow - shoulder) == pytest.approx(arm.l1, abs=1e-6)
    # out of reach: pulled in along the line to 99.5 % of the reach, pointing at the target
    far = np.stack([shoulder + [-2.0, 0.0, 0.0]] * 2)
    arm.solve(local, transl, far, pole)
    heads, _ = sk.fk(local, transl)
    wrist = heads[0, arm.ie] - shoulder
    assert np.linalg.norm(wrist) == pytest.approx(0.995 * arm.reach, rel=1e-6)
    np.testing.assert_allclose(wrist / np.linalg.norm(wrist), [-1.0, 0.0, 0.0], atol=1e-6)


def test_ground_truth_distances_sign_by_winding_number_at_any_depth(body_model):
    """Two average bodies, the second turned to face the first and pushed 10 cm into it (one
    frame): the stored distances (m) agree with igl's winding-number signed distance on every
    vertex inside the partner, however deep (the banded pseudonormal query alone leaves vertices
    deeper than DISTANCE_BAND as NaN, out of the contract's sight), and outside within the band."""
    import igl

    from dualhuman_builder.sim.quality import penetration_depth
    from dualhuman_builder.sim.scenes import DISTANCE_BAND, ground_truth_distances
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    J = len(body_model.bone_names)
    shape = body_model.default_shape().cpu().numpy()
    pose_b = np.zeros((1, J, 3))
    pose_b[0, 0] = [0.0, np.pi, 0.0]  # facing -Z, towards the first body
    tracks = [BodyTrack.from_model(body_model, pose, np.array([[0.0, 0.0, z]]), shape, FPS, actor=name)
              for pose, z, name in ((np.zeros((1, J, 3)), 0.0, "a"), (pose_b, 0.10, "b"))]  # fmt: skip
    seq = InteractionSequence(tuple(tracks))
    dist = ground_truth_distances(seq)
    assert dist[0].shape == (1, body_model.num_vertices) and dist[0].dtype == np.float16
    faces = _closed_mesh(body_model).astype(np.int64)
    on_surface = np.unique(faces)  # eyes and mouth interior are not queried by the winding sign
    va, vb = (t.vertices()[0].astype(np.float64) for t in tracks)
    ref = igl.signed_distance(va[on_surface], vb, faces, sign_type=igl.SIGNED_DISTANCE_TYPE_WINDING_NUMBER)[0]
    stored = dist[0][0, on_surface].astype(np.float64)
    inside = ref < -1e-4
    assert inside.sum() > 100 and -ref.min() > DISTANCE_BAND + 0.02  # deeper than the band
    np.testing.assert_allclose(stored[inside], ref[inside], atol=2e-4)  # float16 storage
    near_out = (ref > 1e-4) & (ref < DISTANCE_BAND - 1e-3)
    np.testing.assert_allclose(stored[near_out], ref[near_out], atol=2e-4)
    # the contract's penetration is the deepest vertex, not the band
    assert penetration_depth(dist)[0] == pytest.approx(-ref.min(), abs=2e-4)


def test_contact_corrections_ease_in_and_out(body_model):
    """The contact correction's offsets ease over CONTACT_EASE_S at both ends of a contact
    instead of switching in one frame: the hug's pelvises (whose gap the torso correction
    closes) never accelerate like a jump: under 5 m/s^2, where walking stays under 3 m/s^2 and a
    4 cm correction switched on in one frame at 15 fps reads 9 m/s^2."""
    from dualhuman_builder.sim.scenes import _ease_out

    # the easing itself: contact values carried onto the guard frames, fading to 0, continuously
    frames = np.zeros(30, bool)
    frames[10:20] = True
    guard = np.zeros(30, bool)
    guard[2:28] = True
    guard &= ~frames
    vals = np.where(frames, -0.08, 0.0)
    eased = _ease_out(vals, frames, guard, ramp=6.0)
    assert eased[9] == pytest.approx(-0.08 * (1 - (1 / 6) ** 3 * (10 - 15 / 6 + 6 / 36)))
    assert eased[3] == 0.0 and eased[26] == 0.0 and (eased[~guard] == 0).all()
    both = np.where(frames, vals, eased)
    assert np.abs(np.diff(both)).max() < 0.03 and np.abs(np.diff(both, 2)).max() < 0.015
    for seed in (0, 1):
        sc = scene_of("hug", seed)
        for track in sc.sequence.actors:
            acc = np.linalg.norm(np.diff(np.array(track.transl), 2, axis=0), axis=1) * sc.sequence.fps**2
            assert acc.max() < 5.0, f"seed {seed}: pelvis acceleration {acc.max():.1f} m/s^2 at frame {acc.argmax() + 1}"

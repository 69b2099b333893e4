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

"""269-dim motion features, their inverse, statistics, mirroring, and the InterHuman 262 converter."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dualhuman_builder.body.joints import JOINT22_NAMES, JOINT22_PARENTS
from dualhuman_builder.export.features import (
    CHAIN_FIRST,
    FEATURE_DIM,
    FEATURE_SCHEMA,
    REST_DIRECTIONS,
    FeatureLayout,
    canonicalize,
    facing_yaw,
    feature_stats,
    humanml3d_rotations,
    local_rotations,
    mirror_features,
    mirror_joints,
    mirror_text,
    motion_features,
    recover_joints,
    resample_joints,
    root_facing,
)
from dualhuman_builder.export.interhuman import (
    INTERHUMAN_DIM,
    INTERHUMAN_SCHEMA,
    canonicalize_pair,
    interhuman_features,
    recover_interhuman,
)

MM = 1e-3


@pytest.fixture(scope="module")
def handshake():
    """Both actors' joints (T, 22, 3) of a ground-truth handshake at 20 fps (built once, ~20 s)."""
    from dualhuman_builder.sim.scenes import SceneParams, make_scene

    seq = make_scene(SceneParams(type="handshake", seed=0, fps=20)).sequence
    return seq.actors[0].joints(), seq.actors[1].joints()


def _walk(seed=0, frames=120, fps=20.0, template=None):
    """A body walking a random path while turning (several full turns), with moving limbs."""
    rng = np.random.default_rng(seed)
    if template is None:  # a crude standing skeleton facing +Z, left = +X
        template = np.array([
            [0, .95, 0], [.09, .9, 0], [-.09, .9, 0], [0, 1.07, 0], [.1, .5, 0], [-.1, .5, 0], [0, 1.2, 0],
            [.1, .08, -.03], [-.1, .08, -.03], [0, 1.3, 0], [.1, .02, .1], [-.1, .02, .1], [0, 1.5, 0],
            [.08, 1.42, 0], [-.08, 1.42, 0], [0, 1.62, .03], [.18, 1.42, 0], [-.18, 1.42, 0],
            [.2, 1.15, 0], [-.2, 1.15, 0], [.21, .9, .05], [-.21, .9, .05]])  # fmt: skip
    yaw = 0.7 + np.cumsum(rng.normal(0.25, 0.1, frames))  # ~ 4.8 turns over the sequence
    speed = 1.2 / fps
    root = np.cumsum(np.stack([speed * np.sin(yaw), np.zeros(frames), speed * np.cos(yaw)], -1), 0)
    root += [3.0, 0.0, -1.0]
    t = np.arange(frames)[:, None, None] / fps
    wiggle = 0.06 * np.sin(2 * np.pi * (1.0 + rng.random((1, 22, 3))) * t + 6.28 * rng.random((1, 22, 3)))
    wiggle[:, 0] = 0.0
    local = template[None] + wiggle
    local[..., 1] += 0.02 * np.sin(2 * np.pi * 2 * t[..., 0])
    c, s = np.cos(yaw)[:, None], np.sin(yaw)[:, None]
    world = np.stack([c * local[..., 0] + s * local[..., 2], local[..., 1], -s * local[..., 0] + c * local[..., 2]], -1)
    return (world + root[:, None]).astype(np.float32)


# ------------------------------------------------------------------------------------- schema
def test_schema_covers_every_dimension_once():
    assert FEATURE_SCHEMA[0]["start"] == 0 and FEATURE_SCHEMA[-1]["stop"] == FEATURE_DIM == 269
    for prev, nxt in zip(FEATURE_SCHEMA, FEATURE_SCHEMA[1:]):
        assert prev["stop"] == nxt["start"]
    attr = {"ric_positions": "RIC", "rotations_6d": "ROTATIONS"}
    for f in FEATURE_SCHEMA:
        assert int(np.prod(f["shape"])) == f["stop"] - f["start"] and f["units"] and f["meaning"]
        assert getattr(FeatureLayout, attr.get(f["name"], f["name"].upper())) == slice(f["start"], f["stop"])
    assert FeatureLayout.ROTATIONS == slice(67, 193) and FeatureLayout.FOOT_CONTACTS == slice(259, 263)
    assert [f["stop"] for f in INTERHUMAN_SCHEMA] == [66, 132, 258, 262]


# ------------------------------------------------------------------------------ round trips
@pytest.mark.slow
@pytest.mark.parametrize("world", [True, False])
def test_round_trip_handshake(handshake, world):
    for joints in handshake:
        f = motion_features(joints, fps=20)
        assert f.shape == (len(joints) - 1, 269) and f.dtype == np.float32
        back = recover_joints(f, world=world)
        want = joints if world else canonicalize(joints)[0]
        assert back.shape == joints.shape
        assert np.linalg.norm(back - want, axis=-1).max() < 1 * MM


@pytest.mark.parametrize("smoothing", [0.0, 1.0])
def test_round_trip_turning_walk(smoothing):
    joints = _walk()
    assert np.ptp(facing_yaw(joints)) > 4 * 2 * np.pi  # really turns, through +-pi many times
    f = motion_features(joints, fps=20, facing_smoothing_s=smoothing)
    err_w = np.linalg.norm(recover_joints(f) - joints, axis=-1).max()
    err_c = np.linalg.norm(recover_joints(f, world=False) - canonicalize(joints)[0], axis=-1).max()
    assert err_w < 1 * MM and err_c < 1 * MM
    # the features are recomputable from the recovered positions
    np.testing.assert_allclose(motion_features(recover_joints(f), fps=20, facing_smoothing_s=smoothing), f, atol=2e-4)


def test_canonical_frame_and_extra_dims():
    joints = _walk(seed=3)
    f = motion_features(joints, fps=20)
    canon, yaw0, t0 = canonicalize(joints)
    assert abs(canon[..., 1].min()) < 1e-9 and np.allclose(canon[0, 0, [0, 2]], 0.0)
    assert abs(facing_yaw(canon[:1])[0]) < 1e-9  # frame 0 faces +Z
    np.testing.assert_allclose(f[:, 263:269], np.tile([np.sin(yaw0), np.cos(yaw0), *t0, 0.0], (len(f), 1)), atol=1e-6)
    assert t0[1] == pytest.approx(float(joints[..., 1].min()), abs=1e-6)
    # the 263 alone recover the canonical motion; a rotated/translated copy gives the same 263
    np.testing.assert_allclose(recover_joints(f[:, :263], world=False), recover_joints(f, world=False))
    moved = Rotation.from_euler("y", 1.1).apply(joints.reshape(-1, 3)).reshape(joints.shape) + [5.0, 0.3, -2.0]
    g = motion_features(moved, fps=20)
    np.testing.assert_allclose(g[:, :263], f[:, :263], atol=1e-4)
    assert np.arctan2(g[0, 263], g[0, 264]) == pytest.approx(np.angle(np.exp(1j * (yaw0 + 1.1))), abs=1e-5)


def test_matches_humanml3d_recover_from_ric_convention():
    """HumanML3D's published inverse (half-angle quaternion about y, re-done with scipy) on our 263."""
    joints = _walk(seed=1)
    f = motion_features(joints, fps=20).astype(np.float64)
    ang = np.concatenate([[0.0], np.cumsum(f[:-1, 0])])  # r_rot_ang, quaternion (w=cos a, y=sin a)
    inv = Rotation.from_quat(np.stack([0 * ang, np.sin(ang), 0 * ang, np.cos(ang)], -1)).inv()
    r_pos = np.zeros((len(f), 3))
    r_pos[1:, [0, 2]] = f[:-1, 1:3]
    r_pos = np.cumsum(inv.apply(r_pos), axis=0)
    r_pos[:, 1] = f[:, 3]
    ric = f[:, 4:67].reshape(len(f), 21, 3)
    pos = np.stack([inv[i].apply(ric[i]) for i in range(len(f))]) + (r_pos * [1, 0, 1])[:, None]
    hml = np.concatenate([r_pos[:, None], pos], axis=1)
    np.testing.assert_allclose(hml, recover_joints(f, world=False)[:-1], atol=1e-5)


def test_rotations_rebuild_bone_directions():
    joints = _walk(seed=2, frames=30).astype(np.float64)
    canon, yaw0, _ = canonicalize(joints)
    psi = root_facing(joints, 20.0) - yaw0
    loc = humanml3d_rotations(canon, psi)
    f = motion_features(joints, fps=20)
    six = f[:, FeatureLayout.ROTATIONS].reshape(-1, 21, 6)
    np.testing.assert_allclose(six[..., :3], loc[:-1, :, :, 0], atol=1e-6)
    np.testing.assert_allclose(np.linalg.det(loc), 1.0, atol=1e-9)
    root = Rotation.from_euler("y", -psi[:, None]).as_matrix()  # HumanML3D's root rotation: facing -> +Z
    glob = [root]
    for j in range(1, 22):
        glob.append((root if j in CHAIN_FIRST else glob[JOINT22_PARENTS[j]]) @ loc[:, j - 1])
        bone = canon[:, j] - canon[:, JOINT22_PARENTS[j]]
        np.testing.assert_allclose(glob[j] @ REST_DIRECTIONS[j], bone / np.linalg.norm(bone, axis=-1, keepdims=True),
                                   atol=1e-9, err_msg=JOINT22_NAMES[j])  # fmt: skip
    assert CHAIN_FIRST == (1, 2, 3, 13, 14)  # the collars hang from the root, as in HumanML3D's chains


def test_foot_contacts_follow_foot_speed():
    joints = _walk(seed=4, frames=40).astype(np.float64)
    joints[:20, 7] = joints[0, 7]  # left ankle planted for 20 frames, then moves fast
    joints[20:, 7] = joints[0, 7] + np.arange(20)[:, None] * [0.1, 0, 0]
    f = motion_features(joints, fps=20)
    assert (f[:19, 259] == 1).all() and (f[20:, 259] == 0).all()
    # threshold scales with fps: 0.05 m/frame is 1 m/s at 20 fps (no contact) but 0.5 m/s at 10 fps
    joints[:, 7] = joints[0, 7] + np.arange(40)[:, None] * [0.05, 0, 0]
    assert (motion_features(joints, fps=20)[:, 259] == 0).all()
    assert (motion_features(joints, fps=10)[:, 259] == 1).all()


# ------------------------------------------------------------------------------------- stats
def test_feature_stats_grouped_std():
    a, b = motion_features(_walk(seed=5), 20), motion_features(_walk(seed=6, frames=60), 20)
    mean, std = feature_stats([a, b])
    both = np.concatenate([a, b]).astype(np.float64)
    assert mean.shape == std.shape == (269,) and mean.dtype == np.float32
    np.testing.assert_allclose(mean, both.mean(0), atol=1e-6)
    np.testing.assert_allclose(std[4:67], both[:, 4:67].std(0).mean(), rtol=1e-5)  # one std for the ric group
    assert std[3] == pytest.approx(both[:, 3].std(), rel=1e-5)
    assert std[268] == 1.0  # spare dim is constant -> 1
    assert np.isfinite((both - mean) / std).all()


# --------------------------------------------------------------------------------- mirroring
def test_mirror_features_equal_features_of_mirrored_joints(handshake):
    for joints in (_walk(seed=7), handshake[0]):
        f = motion_features(joints, fps=20)
        fm = motion_features(mirror_joints(joints), fps=20)
        np.testing.assert_allclose(mirror_features(f), fm, atol=1e-5)
        np.testing.assert_allclose(mirror_features(mirror_features(f)), f, atol=0)
    left = _walk(seed=8)
    assert np.allclose(mirror_joints(left)[:, 1, 0], -left[:, 2, 0])  # left hip <- mirrored right hip


def test_mirror_text():
    assert mirror_text("He raises his left hand.") == "He raises his right hand."
    assert mirror_text("Left, RIGHT, Right and left") == "Right, LEFT, Left and right"
    assert mirror_text("steps leftward then rightwards, the leftmost one") == "steps rightward then leftwards, the rightmost one"
    assert mirror_text("a right-handed spin clockwise, then counterclockwise") == "a left-handed spin counterclockwise, then clockwise"
    assert mirror_text("all right, come right away; the leftover bright light") == "all right, come right away; the leftover bright light"


# ---------------------------------------------------------------------------------- InterHuman
def test_interhuman_round_trip_and_relative_placement(handshake):
    a, b = handshake
    res = interhuman_features(a, b, fps=20)  # resampled to 30 fps
    assert res.fps == 30.0
    ra, rb = resample_joints(a, 20, 30), resample_joints(b, 20, 30)
    assert len(ra) == 119 and res.person1.shape == res.person2.shape == (118, INTERHUMAN_DIM)
    ca, cb, tr = canonicalize_pair(ra, rb)
    pa, pb = recover_interhuman(res.person1), recover_interhuman(res.person2)
    assert np.linalg.norm(pa - ca, axis=-1).max() < 1 * MM and np.linalg.norm(pb - cb, axis=-1).max() < 1 * MM
    # person 1 canonical: floor, root XZ at origin, facing +Z (hips) at frame 0; person 2 same transform
    assert abs(pa[..., 1].min()) < 1e-6 and np.abs(pa[0, 0, [0, 2]]).max() < 1e-6
    assert abs(facing_yaw(pa[:1], (2, 1))[0]) < 1e-5
    np.testing.assert_allclose(pb[:, 0] - pa[:, 0], Rotation.from_euler("y", -tr.yaw0).apply(rb[:, 0] - ra[:, 0]), atol=1e-5)
    np.testing.assert_allclose(np.linalg.norm(pb[:, None] - pa[:, :, None], axis=-1),
                               np.linalg.norm(rb[:, None] - ra[:, :, None], axis=-1), atol=1 * MM)  # fmt: skip
    back = recover_interhuman(res.person2, res.transform)
    assert np.linalg.norm(back - rb, axis=-1).max() < 1 * MM
    # actor 1 faces actor 0 across 1.8 m: in the shared frame it stands ~1.8 m ahead (+Z), facing -Z
    assert pb[0, 0, 2] == pytest.approx(1.8, abs=0.05) and abs(np.cos(facing_yaw(pb[:1])[0]) + 1) < 0.05


def test_interhuman_rotations_and_contacts():
    a, b = _walk(seed=9, frames=60), _walk(seed=10, frames=60)
    res = interhuman_features(a, b, fps=20, target_fps=None)
    c = canonicalize_pair(a, b)[0]
    rot = local_rotations(c[:-1], root_facing(c, 20.0)[:-1])  # facing-frame swings, no twist
    # InterHuman's 6D: rot_mat[..., :2] flattened by row (r00, r01, r10, r11, r20, r21)
    np.testing.assert_allclose(res.person1[:, 132:258], rot[..., :2].reshape(len(rot), -1), atol=1e-5)
    np.testing.assert_allclose(res.person1[:, 66:132].reshape(-1, 22, 3),
                               np.diff(canonicalize_pair(a, b)[0], axis=0), atol=1e-6)  # fmt: skip
    # person 2 0.2 m higher (it shares person 1's floor): its contacts vanish (height limits)
    res2 = interhuman_features(a, b + np.float32([0, 0.2, 0]), fps=20, target_fps=None)
    assert res.person2[:, 258:262].any() and not res2.person2[:, 258:262].any()
    np.testing.assert_array_equal(res2.person1, res.person1)


# ---------------------------------------------------------------------------------- bad input
def test_bad_input_raises():
    good = _walk(frames=10)
    with pytest.raises(ValueError, match=r"shape \(T, 22, 3\), got \(10, 21, 3\)"):
        motion_features(good[:, :21], 20)
    with pytest.raises(ValueError, match="at least 2 frames, got 1"):
        motion_features(good[:1], 20)
    bad = good.copy()
    bad[4, 3, 1] = np.nan
    with pytest.raises(ValueError, match=r"NaN or inf values at frames \[4\]"):
        motion_features(bad, 20)
    with pytest.raises(ValueError, match="fps must be a positive number"):
        motion_features(good, 0)
    with pytest.raises(ValueError, match="facing undefined"):
        motion_features(np.zeros((5, 22, 3)), 20)
    with pytest.raises(ValueError, match=r"shape \(N, 269\), got \(4, 250\)"):
        recover_joints(np.zeros((4, 250)))
    with pytest.raises(ValueError, match="at least 1 row"):
        recover_joints(np.zeros((0, 269)))
    f = motion_features(good, 20)
    f[2, 10] = np.inf
    with pytest.raises(ValueError, match=r"NaN or inf values in rows \[2\]"):
        recover_joints(f)
    with pytest.raises(ValueError, match="initial facing"):
        recover_joints(np.zeros((3, 269)))
    with pytest.raises(ValueError, match="empty list"):
        feature_stats([])
    with pytest.raises(ValueError, match="same shape"):
        interhuman_features(good, good[:5], 20)
    with pytest.raises(ValueError, match="fewer than 2 frames"):
        interhuman_features(good[:2], good[:2], fps=100)
    with pytest.raises(ValueError, match=r"shape \(N, 262\)"):
        recover_interhuman(np.zeros((3, 263)))
    with pytest.raises(ValueError, match="must be a str"):
        mirror_text(None)

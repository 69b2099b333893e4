"""HumanML3D's rotation path recomputed independently from its published definitions.

``process_file`` / ``Skeleton.inverse_kinematics_np`` (EricGuo5513/HumanML3D) and ``recover_from_rot``
/ ``forward_kinematics_cont6d`` (EricGuo5513/text-to-motion ``utils/motion_process.py``), re-done here
with quaternions and scipy: the rotation features [67:193] must be what HumanML3D's inverse kinematics
gives for our root facing, and HumanML3D's forward kinematics must rebuild our joints from them.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dualhuman_builder.export.features import (
    FeatureLayout,
    canonicalize,
    motion_features,
    root_facing,
)

MM = 1e-3
#: HumanML3D's ``t2m_kinematic_chain`` and ``t2m_raw_offsets``.
CHAINS = [[0, 2, 5, 8, 11], [0, 1, 4, 7, 10], [0, 3, 6, 9, 12, 15], [9, 14, 17, 19, 21], [9, 13, 16, 18, 20]]
RAW_OFFSETS = np.array([
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, -1, 0],
    [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1],
    [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0]], dtype=np.float64)  # fmt: skip
PARENTS = [-1] * 22
for _chain in CHAINS:
    for _a, _b in zip(_chain, _chain[1:]):
        PARENTS[_b] = _a
#: A standing body facing +Z, its left towards +X (HumanML3D's joint order).
TEMPLATE = np.array([
    [0, .95, 0], [.09, .9, 0], [-.09, .9, 0], [0, 1.07, 0], [.1, .5, 0], [-.1, .5, 0], [0, 1.2, 0],
    [.1, .08, -.03], [-.1, .08, -.03], [0, 1.3, 0], [.1, .02, .1], [-.1, .02, .1], [0, 1.5, 0],
    [.08, 1.42, 0], [-.08, 1.42, 0], [0, 1.62, .03], [.18, 1.42, 0], [-.18, 1.42, 0],
    [.2, 1.15, 0], [-.2, 1.15, 0], [.21, .9, .05], [-.21, .9, .05]])  # fmt: skip


def _quat(w, xyz) -> Rotation:
    """Rotation of the quaternion ``(w, x, y, z)`` (HumanML3D's order)."""
    return Rotation.from_quat(np.concatenate([xyz, np.asarray(w)[..., None]], axis=-1))


def _qbetween(u, v) -> Rotation:
    """HumanML3D's ``qbetween``: w = |u||v| + u.v, xyz = u x v, normalised."""
    w = np.sqrt((u**2).sum(-1) * (v**2).sum(-1)) + (u * v).sum(-1)
    return _quat(w, np.cross(u, v))


def _upstream_rotations(canon: np.ndarray, psi: np.ndarray) -> np.ndarray:
    """``inverse_kinematics_np``'s local rotations (T, 22, 3, 3) with root quaternion R_y(-psi)."""
    root = Rotation.from_euler("y", -psi[:, None])  # qbetween(forward, +Z)
    out = np.zeros((len(canon), 22, 3, 3))
    out[:, 0] = root.as_matrix()
    for chain in CHAINS:
        r = root
        for a, b in zip(chain, chain[1:]):
            v = canon[:, b] - canon[:, a]
            v = v / np.linalg.norm(v, axis=-1, keepdims=True)
            loc = r.inv() * _qbetween(np.broadcast_to(RAW_OFFSETS[b], v.shape), v)
            out[:, b] = loc.as_matrix()
            r = r * loc
    return out


def _cont6d_to_matrix(six: np.ndarray) -> np.ndarray:
    x = six[..., 0:3] / np.linalg.norm(six[..., 0:3], axis=-1, keepdims=True)
    z = np.cross(x, six[..., 3:6])
    z = z / np.linalg.norm(z, axis=-1, keepdims=True)
    return np.stack([x, np.cross(z, x), z], axis=-1)  # columns x, y, z


def _recover_from_rot(f: np.ndarray, skel_joints: np.ndarray) -> np.ndarray:
    """``recover_from_rot`` of features ``f (N, 263+)`` with the bone lengths of ``skel_joints (N, 22, 3)``
    (``forward_kinematics_cont6d(..., skel_joints=...)``): joints (N, 22, 3), canonical frame."""
    n = len(f)
    ang = np.concatenate([[0.0], np.cumsum(f[:-1, 0])])
    r_rot = _quat(np.cos(ang), np.stack([0 * ang, np.sin(ang), 0 * ang], -1))
    r_pos = np.zeros((n, 3))
    r_pos[1:, [0, 2]] = f[:-1, 1:3]
    r_pos = np.cumsum(r_rot.inv().apply(r_pos), axis=0)
    r_pos[:, 1] = f[:, 3]
    root_mat = r_rot.as_matrix()
    six = np.concatenate([np.concatenate([root_mat[..., 0], root_mat[..., 1]], -1)[:, None],
                          f[:, FeatureLayout.ROTATIONS].reshape(n, 21, 6)], axis=1)  # fmt: skip
    mats = _cont6d_to_matrix(six)
    offsets = RAW_OFFSETS * np.linalg.norm(skel_joints - skel_joints[:, [max(p, 0) for p in PARENTS]], axis=-1)[..., None]
    joints = np.zeros((n, 22, 3))
    joints[:, 0] = r_pos
    for chain in CHAINS:
        m = mats[:, 0]
        for a, b in zip(chain, chain[1:]):
            m = m @ mats[:, b]
            joints[:, b] = (m @ offsets[:, b, :, None])[..., 0] + joints[:, a]
    return joints


def _world(local: np.ndarray, yaw: np.ndarray, root: np.ndarray) -> np.ndarray:
    """``local (T, 22, 3)`` turned by ``yaw (T,)`` about +Y, then moved by ``root (T, 3)``."""
    return np.einsum("tij,tkj->tki", Rotation.from_euler("y", yaw[:, None]).as_matrix(), local) + root[:, None]


def _body(frames: int, yaw: np.ndarray, root: np.ndarray, seed: int = 0) -> np.ndarray:
    """A rigid-limbed body: each bone of :data:`TEMPLATE` swung by a smooth random rotation, then
    turned by ``yaw (T,)`` about +Y and placed at ``root (T, 3)`` (its root joint's XZ)."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / 20.0
    local = np.repeat(TEMPLATE[None], frames, axis=0).copy()
    for chain in CHAINS:
        for a, b in zip(chain, chain[1:]):
            rv = 0.5 * np.sin(2 * np.pi * (0.3 + rng.random(3)) * t[:, None] + 6.28 * rng.random(3))
            bone = Rotation.from_rotvec(rv).apply(TEMPLATE[b] - TEMPLATE[a])
            local[:, b] = local[:, a] + bone
    local[..., 1] -= local[..., 1].min() - 0.01
    return _world(local - TEMPLATE[0] * [1, 0, 1], yaw, root)


def _check(joints: np.ndarray, upstream_ik: bool = True, tol_mm: float = 0.1) -> None:
    """Our rotation features equal HumanML3D's inverse kinematics (``upstream_ik``; it gives NaN for a
    bone exactly against its rest direction) and its ``recover_from_rot`` rebuilds our joints."""
    f = motion_features(joints, fps=20).astype(np.float64)
    canon, yaw0, _ = canonicalize(joints)
    psi = root_facing(joints, 20.0) - yaw0
    if upstream_ik:
        up = _upstream_rotations(canon[:-1], psi[:-1])
        six = np.concatenate([up[..., 0], up[..., 1]], axis=-1)[:, 1:]
        np.testing.assert_allclose(f[:, FeatureLayout.ROTATIONS].reshape(-1, 21, 6), six, atol=1e-5)
    rec = _recover_from_rot(f, canon[:-1])
    err = np.linalg.norm(rec - canon[:-1], axis=-1)
    assert err.max() < tol_mm * MM, f"recover_from_rot off by {err.max() / MM:.2f} mm at joint {err.max(0).argmax()}"


def test_recover_from_rot_turning_in_place_through_360():
    frames = 60
    yaw = np.linspace(0.0, 2.4 * np.pi, frames)  # passes facing -Z and a full turn
    _check(_body(frames, yaw, np.tile([0.5, 0.0, -2.0], (frames, 1)), seed=1))


def test_recover_from_rot_walking_and_turning():
    frames, rng = 80, np.random.default_rng(3)
    yaw = -0.4 + np.cumsum(rng.normal(0.12, 0.05, frames))
    root = np.cumsum(np.stack([0.06 * np.sin(yaw), 0 * yaw, 0.06 * np.cos(yaw)], -1), axis=0) + [2.0, 0.0, 1.0]
    _check(_body(frames, yaw, root, seed=4))


@pytest.mark.parametrize("turn", [0.0, 0.05])
@pytest.mark.parametrize("arm_up", [False, True])
def test_recover_from_rot_facing_exactly_minus_z(turn, arm_up):
    frames = 30
    yaw = np.pi + turn * np.arange(frames)  # world facing exactly -Z at frame 0
    body = _body(frames, yaw, np.tile([-1.0, 0.0, 0.3], (frames, 1)), seed=7)
    if arm_up:  # left upper arm and forearm straight up: exactly against their rest direction
        body[:, 18] = body[:, 16] + [0.0, 0.25, 0.0]
        body[:, 20] = body[:, 18] + [0.0, 0.25, 0.0]
    _check(body, upstream_ik=not arm_up)


@settings(max_examples=25, deadline=None)
@given(yaw0=st.floats(-np.pi, np.pi), rate=st.floats(-0.4, 0.4), seed=st.integers(0, 1000))
def test_recover_from_rot_any_start_facing_and_turn_rate(yaw0, rate, seed):
    frames = 24
    _check(_body(frames, yaw0 + rate * np.arange(frames), np.tile([0.3, 0.0, 0.7], (frames, 1)), seed=seed))

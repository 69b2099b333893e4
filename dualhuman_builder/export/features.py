"""The 269-dim per-person motion features (HumanML3D's 263 + 6) and their exact inverse.

Input: 22 joints in HumanML3D order (:data:`~dualhuman_builder.body.joints.JOINT22_NAMES`),
``(T, 22, 3)`` world metres, +Y up, floor y = 0, a body at identity facing +Z with its left side
towards +X (:mod:`dualhuman_builder.conventions`). The features keep the joints' own bone lengths;
the converters can retarget to HumanML3D's reference skeleton first
(:mod:`dualhuman_builder.export.retarget`, ``--retarget humanml3d``).

Canonicalisation (per sequence, as HumanML3D): ``c = R_y(-yaw0) (w - t0)`` with
``t0 = (root_x(0), floor_y, root_z(0))``, ``floor_y`` the lowest joint height over the sequence and
``yaw0`` the raw facing of frame 0, so the canonical body stands on y = 0, its root starts above the
origin and it faces +Z at frame 0.

Facing: the horizontal forward ``up x across`` with ``across = (r_hip - l_hip) + (r_shoulder -
l_shoulder)`` (joints ``[2, 1, 17, 16]``), as the yaw ``atan2(f_x, f_z)`` (0 = facing +Z). The per
frame root facing ``psi(t)`` is the unwrapped raw yaw smoothed by a Gaussian of
``facing_smoothing_s`` seconds (HumanML3D: 20 frames at 20 fps = 1 s), shifted by a constant so that
``psi(0)`` equals the raw yaw of frame 0. That shift is what makes the inverse exact: HumanML3D
forces the root rotation of frame 0 to identity after smoothing, which its ``recover_from_ric``
then cannot undo. ``R_y(a)`` is the rotation by ``a`` about +Y (takes +Z to ``(sin a, 0, cos a)``).

Features, ``T - 1`` rows (row ``t`` describes frame ``t`` and the step ``t -> t+1``), canonical
frame, ``psi`` the canonical facing; velocities are per frame at the input ``fps`` (HumanML3D is
20 fps: resample first with :func:`resample_joints` to match its statistics):

* ``[0:1]``     ``-(psi(t+1) - psi(t)) / 2``, rad/frame. HumanML3D's value, ``arcsin`` of the y
  component of the quaternion ``r(t+1) r(t)^-1``: half the per-frame yaw change, sign flipped.
* ``[1:3]``     root XZ velocity ``R_y(-psi(t+1)) (p_0(t+1) - p_0(t))``, local (x, z), m/frame.
* ``[3:4]``     root height above the floor at frame ``t``, m.
* ``[4:67]``    ``R_y(-psi(t)) (p_j(t) - (p_0x(t), 0, p_0z(t)))`` for joints 1..21, m ("ric"; y
  stays the height above the floor).
* ``[67:193]``  21 local joint rotations in HumanML3D's convention, 6D (first two columns of the
  matrix), see :func:`humanml3d_rotations`: HumanML3D's ``recover_from_rot`` rebuilds the joints from
  them, dims [0:4] and the bone lengths.
* ``[193:259]`` ``R_y(-psi(t)) (p_j(t+1) - p_j(t))`` for all 22 joints, m/frame.
* ``[259:263]`` foot contacts (joints 7, 10, 8, 11: left ankle, left foot, right ankle, right foot):
  1 where ``|p_j(t+1) - p_j(t)|^2 < (contact_speed / fps)^2`` (HumanML3D: 0.002 m^2 at 20 fps).
* ``[263:269]`` ``[sin yaw0, cos yaw0, t0_x, t0_y, t0_z, 0]``: the transform back to the world
  (camera-view) motion, ``w = R_y(yaw0) c + t0``; ``t0_y`` is ``floor_y``. Constant over rows.

Rows 0..N-1 of :func:`recover_joints` are exactly HumanML3D's ``recover_from_ric`` of the first 263
dims; frame N (the last input frame) is added from the joint velocities of the last row, so the round
trip returns all ``T`` input frames.
"""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d

from dualhuman_builder.body.joints import JOINT22_NAMES, JOINT22_PARENTS

NUM_JOINTS = 22
HUMANML3D_DIM = 263
FEATURE_DIM = 269
HUMANML3D_FPS = 20.0

#: Joints defining the facing: right hip, left hip, right shoulder, left shoulder.
FACE_JOINTS = (2, 1, 17, 16)
#: Foot joints whose contacts are features [259:261] (left ankle, left foot) and [261:263] (right).
FEET_LEFT = (7, 10)
FEET_RIGHT = (8, 11)
#: HumanML3D's contact threshold, squared metres per frame at 20 fps, and the speed it amounts to.
HUMANML3D_CONTACT_THRESHOLD = 0.002
CONTACT_SPEED = float(np.sqrt(HUMANML3D_CONTACT_THRESHOLD) * HUMANML3D_FPS)  # ~0.894 m/s
#: Gaussian sigma of the facing smoothing, seconds (HumanML3D: 20 frames at 20 fps).
FACING_SMOOTHING_S = 1.0

#: Rest direction of the bone ending at each joint (HumanML3D's ``t2m_raw_offsets``), Y-up,
#: +X = the body's left, +Z = forward. Row 0 (root) is unused.
REST_DIRECTIONS = np.array([
    [0, 0, 0], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, -1, 0], [0, 1, 0], [0, -1, 0],
    [0, -1, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [0, 1, 0], [1, 0, 0], [-1, 0, 0], [0, 0, 1],
    [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0], [0, -1, 0],
], dtype=np.float64)  # fmt: skip

#: Joint index after left/right mirroring (each left joint swaps with its right twin).
MIRROR_PERM = np.array([0, 2, 1, 3, 5, 4, 6, 8, 7, 9, 11, 10, 12, 14, 13, 15, 17, 16, 19, 18, 21, 20])

_PARENTS = np.asarray(JOINT22_PARENTS)
# rotation by pi used when a bone points exactly against its rest direction: about a coordinate
# axis perpendicular to the rest direction (mirror-consistent)
_FLIP_AXIS = np.array([[0, 1, 0] if abs(r[0]) > 0 else [1, 0, 0] for r in REST_DIRECTIONS], dtype=np.float64)


@dataclass(frozen=True)
class FeatureField:
    """One named slice of the feature vector."""

    name: str
    start: int
    stop: int
    shape: tuple[int, ...]
    units: str
    meaning: str

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)


FEATURE_FIELDS: tuple[FeatureField, ...] = (
    FeatureField("root_angular_velocity", 0, 1, (1,), "rad/frame",
                 "-(psi(t+1) - psi(t)) / 2: half the per-frame change of the root facing yaw psi about +Y, "
                 "negated (HumanML3D's arcsin of the y component of r(t+1) r(t)^-1)"),
    FeatureField("root_linear_velocity", 1, 3, (2,), "m/frame",
                 "root displacement t -> t+1 in the root facing frame of t+1, (x = left, z = forward)"),
    FeatureField("root_height", 3, 4, (1,), "m", "root height above the canonical floor at frame t"),
    FeatureField("ric_positions", 4, 67, (21, 3), "m",
                 "joints 1..21 minus the root's (x, 0, z), rotated into the root facing frame of t"),
    FeatureField("rotations_6d", 67, 193, (21, 6), "1",
                 "local rotation of joints 1..21 as HumanML3D (swing of each bone from its rest direction in the "
                 "canonical frame, relative to the previous bone of its HumanML3D chain; a chain's first bone, "
                 "collars included, is R_y(psi) times its swing), first two matrix columns"),
    FeatureField("joint_velocities", 193, 259, (22, 3), "m/frame",
                 "displacement t -> t+1 of all 22 joints in the root facing frame of t"),
    FeatureField("foot_contacts", 259, 263, (4,), "0/1",
                 "left ankle, left foot, right ankle, right foot: squared displacement t -> t+1 below "
                 "(contact_speed / fps)^2"),
    FeatureField("initial_facing", 263, 265, (2,), "1",
                 "(sin yaw0, cos yaw0): world facing yaw of frame 0 (0 = +Z); constant over rows"),
    FeatureField("initial_translation", 265, 268, (3,), "m",
                 "t0 = (root x at frame 0, floor height, root z at frame 0), world; world = R_y(yaw0) canonical + t0"),
    FeatureField("spare", 268, 269, (1,), "1", "always 0"),
)  # fmt: skip

#: The export schema: one dict per field (name, start, stop, shape, units, meaning).
FEATURE_SCHEMA: list[dict] = [{**asdict(f), "shape": list(f.shape)} for f in FEATURE_FIELDS]


class FeatureLayout:
    """Slices of the 269-dim feature vector (see :data:`FEATURE_SCHEMA`)."""

    ROOT_ANGULAR_VELOCITY = slice(0, 1)
    ROOT_LINEAR_VELOCITY = slice(1, 3)
    ROOT_HEIGHT = slice(3, 4)
    RIC = slice(4, 67)
    ROTATIONS = slice(67, 193)
    JOINT_VELOCITIES = slice(193, 259)
    FOOT_CONTACTS = slice(259, 263)
    INITIAL_FACING = slice(263, 265)
    INITIAL_TRANSLATION = slice(265, 268)
    SPARE = slice(268, 269)
    HUMANML3D = slice(0, 263)
    DIM = FEATURE_DIM


# ---------------------------------------------------------------------------------------- checks
def check_joints(joints, what: str = "joints", min_frames: int = 2) -> np.ndarray:
    """``joints`` as float64 ``(T, 22, 3)``; ValueError on a wrong shape, too few frames, NaN/inf."""
    arr = np.asarray(joints, dtype=np.float64)
    if arr.ndim != 3 or arr.shape[1:] != (NUM_JOINTS, 3):
        raise ValueError(f"{what} must have shape (T, 22, 3), got {arr.shape}")
    if arr.shape[0] < min_frames:
        raise ValueError(f"{what} needs at least {min_frames} frames, got {arr.shape[0]}")
    bad = ~np.isfinite(arr).all(axis=(1, 2))
    if bad.any():
        raise ValueError(f"{what} has NaN or inf values at frames {np.flatnonzero(bad)[:10].tolist()}")
    return arr


def _check_fps(fps, what: str = "fps") -> float:
    try:
        val = float(fps)
    except (TypeError, ValueError):
        raise ValueError(f"{what} must be a positive number, got {fps!r}") from None
    if not np.isfinite(val) or val <= 0:
        raise ValueError(f"{what} must be a positive number, got {fps!r}")
    return val


def _check_features(features, dim: int, what: str = "features") -> np.ndarray:
    arr = np.asarray(features, dtype=np.float64)
    if arr.ndim != 2 or arr.shape[1] != dim:
        raise ValueError(f"{what} must have shape (N, {dim}), got {arr.shape}")
    if arr.shape[0] < 1:
        raise ValueError(f"{what} needs at least 1 row, got 0")
    bad = ~np.isfinite(arr).all(axis=1)
    if bad.any():
        raise ValueError(f"{what} has NaN or inf values in rows {np.flatnonzero(bad)[:10].tolist()}")
    return arr


# -------------------------------------------------------------------------------------- geometry
def rot_y(angle) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` by ``angle (...)`` radians about +Y (+Z -> (sin, 0, cos))."""
    a = np.asarray(angle, dtype=np.float64)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def _rotate_y(v: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotate vectors ``v (..., 3)`` by ``angle`` (broadcast against ``v[..., 0]``) about +Y."""
    c, s = np.cos(angle), np.sin(angle)
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return np.stack([c * x + s * z, y, -s * x + c * z], axis=-1)


def facing_yaw(joints, face_joints=FACE_JOINTS) -> np.ndarray:
    """Raw per-frame facing yaw ``(T,)`` radians, unwrapped, of ``joints (T, 22, 3)``.

    Forward = ``up x across``, ``across = (p[r_hip] - p[l_hip]) + (p[r_sh] - p[l_sh])`` (only the
    hips when ``face_joints`` has two entries); yaw = ``atan2(forward_x, forward_z)``, 0 = +Z.
    ValueError when the across vector has no horizontal extent on some frame.
    """
    j = np.asarray(joints, dtype=np.float64)
    across = j[:, face_joints[0]] - j[:, face_joints[1]]
    if len(face_joints) == 4:
        across = across + (j[:, face_joints[2]] - j[:, face_joints[3]])
    horiz = np.hypot(across[:, 0], across[:, 2])
    bad = horiz < 1e-6
    if bad.any():
        raise ValueError(f"facing undefined (hips/shoulders collapsed or vertical) at frames {np.flatnonzero(bad)[:10].tolist()}")
    # forward = (0, 1, 0) x across = (across_z, 0, -across_x)
    return np.unwrap(np.arctan2(across[:, 2], -across[:, 0]))


def root_facing(joints, fps: float, facing_smoothing_s: float = FACING_SMOOTHING_S) -> np.ndarray:
    """Per-frame root facing yaw ``(T,)`` radians: the raw yaw smoothed by a Gaussian of
    ``facing_smoothing_s`` seconds (0: none), shifted so that frame 0 keeps its raw value."""
    raw = facing_yaw(joints)
    sigma = float(facing_smoothing_s) * float(fps)
    if sigma <= 0:
        return raw
    smooth = gaussian_filter1d(raw, sigma, mode="nearest")
    return smooth - smooth[0] + raw[0]


def canonicalize(joints) -> tuple[np.ndarray, float, np.ndarray]:
    """HumanML3D canonicalisation of ``joints (T, 22, 3)`` world metres.

    Returns ``(canonical (T, 22, 3) float64, yaw0, t0 (3,))`` with ``canonical = R_y(-yaw0)(joints - t0)``,
    ``t0 = (root_x(0), floor_y, root_z(0))``, ``floor_y`` the lowest joint height, ``yaw0`` the raw
    facing of frame 0.
    """
    j = check_joints(joints, min_frames=1)
    yaw0 = float(facing_yaw(j[:1])[0])
    t0 = np.array([j[0, 0, 0], j[..., 1].min(), j[0, 0, 2]])
    return _rotate_y(j - t0, -yaw0), yaw0, t0


def _swing(rest: np.ndarray, d: np.ndarray, flip_axis: np.ndarray) -> np.ndarray:
    """Smallest rotations ``(T, J, 3, 3)`` taking unit ``rest (J, 3)`` onto unit ``d (T, J, 3)``;
    a half turn about ``flip_axis (J, 3)`` where ``d`` is exactly opposite to ``rest``."""
    a = np.broadcast_to(rest, d.shape)
    v = np.cross(a, d)
    c = np.einsum("...i,...i->...", a, d)
    k = np.zeros(d.shape + (3,))
    k[..., 0, 1], k[..., 0, 2], k[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    k[..., 1, 0], k[..., 2, 0], k[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    flip = 1.0 + c < 1e-9
    denom = np.where(flip, 1.0, 1.0 + c)
    out = np.eye(3) + k + (k @ k) / denom[..., None, None]
    if flip.any():  # exactly opposite: half turn about a fixed perpendicular axis
        n = np.broadcast_to(flip_axis, d.shape)[flip]
        out[flip] = 2.0 * n[:, :, None] * n[:, None, :] - np.eye(3)
    return out


def local_rotations(joints, psi) -> np.ndarray:
    """Local joint rotations ``(T, 21, 3, 3)`` of joints 1..21, recomputable from positions.

    In the root facing frame (``q = R_y(-psi) p``), the bone ending at joint ``j`` has unit
    direction ``d_j = (q_j - q_parent) / |.|``; its global rotation ``G_j`` is the smallest rotation
    taking :data:`REST_DIRECTIONS` ``[j]`` onto ``d_j`` (a half turn about a fixed perpendicular axis
    if exactly opposite); ``G_root = I`` (the facing frame). The local rotation is
    ``L_j = G_parent(j)^T G_j``, so ``G_j = L_a L_b ... L_j`` along the chain and ``G_j rest_j = d_j``.
    Twist about a bone is not observable from positions and is always zero.
    """
    j = np.asarray(joints, dtype=np.float64)
    q = _rotate_y(j, -np.asarray(psi, dtype=np.float64)[:, None])
    bone = q[:, 1:] - q[:, _PARENTS[1:]]
    length = np.linalg.norm(bone, axis=-1, keepdims=True)
    if (length < 1e-9).any():
        t, b = np.argwhere(length[..., 0] < 1e-9)[0]
        raise ValueError(f"joint {JOINT22_NAMES[b + 1]} coincides with its parent at frame {t}")
    glob = np.empty((len(j), NUM_JOINTS, 3, 3))
    glob[:, 0] = np.eye(3)
    glob[:, 1:] = _swing(REST_DIRECTIONS[1:], bone / length, _FLIP_AXIS[1:])
    return np.swapaxes(glob[:, _PARENTS[1:]], -1, -2) @ glob[:, 1:]


#: HumanML3D's kinematic chains (``t2m_kinematic_chain``): the arms start at spine3 (9).
HUMANML3D_CHAINS = ((0, 2, 5, 8, 11), (0, 1, 4, 7, 10), (0, 3, 6, 9, 12, 15), (9, 14, 17, 19, 21), (9, 13, 16, 18, 20))
#: Joints whose bone is the first of a HumanML3D chain: their rotation is taken relative to the root.
CHAIN_FIRST = tuple(sorted(c[1] for c in HUMANML3D_CHAINS))


def humanml3d_rotations(canonical, psi) -> np.ndarray:
    """Local joint rotations ``(T, 21, 3, 3)`` of joints 1..21 in HumanML3D's convention.

    ``canonical (T, 22, 3)``: joints in the canonical frame; ``psi (T,)``: the root facing yaw there
    (radians, the one dims [0:1] integrate to). The bone ending at joint ``j`` has unit direction
    ``d_j``; its global rotation ``G_j`` is the smallest rotation taking :data:`REST_DIRECTIONS` ``[j]``
    onto ``d_j`` in the canonical frame (a half turn about a fixed perpendicular axis if exactly
    opposite, where HumanML3D gives NaN). As HumanML3D's ``inverse_kinematics_np``, with root rotation
    ``R_y(-psi)`` (facing -> +Z): the first bone of each chain in :data:`HUMANML3D_CHAINS` (hips,
    spine1 and both collars) gets ``L_j = R_y(psi) G_j``, every other ``L_j = G_parent^T G_j``. So
    ``recover_from_rot``'s forward kinematics ``R_y(-psi) L_a ... L_j`` equals ``G_j`` and rebuilds
    the bone. Twist about a bone is not observable from positions and is always zero.
    """
    j = np.asarray(canonical, dtype=np.float64)
    bone = j[:, 1:] - j[:, _PARENTS[1:]]
    length = np.linalg.norm(bone, axis=-1, keepdims=True)
    if (length < 1e-9).any():
        t, b = np.argwhere(length[..., 0] < 1e-9)[0]
        raise ValueError(f"joint {JOINT22_NAMES[b + 1]} coincides with its parent at frame {t}")
    glob = _swing(REST_DIRECTIONS[1:], bone / length, _FLIP_AXIS[1:])  # (T, 21, 3, 3), joint j at j - 1
    out = np.empty_like(glob)
    facing = rot_y(psi)
    for k in range(1, NUM_JOINTS):
        if k in CHAIN_FIRST:
            out[:, k - 1] = facing @ glob[:, k - 1]
        else:
            out[:, k - 1] = np.swapaxes(glob[:, _PARENTS[k] - 1], -1, -2) @ glob[:, k - 1]
    return out


def _to_6d(mats: np.ndarray) -> np.ndarray:
    return np.concatenate([mats[..., :, 0], mats[..., :, 1]], axis=-1)


# -------------------------------------------------------------------------------------- features
def motion_features(joints, fps: float, facing_smoothing_s: float = FACING_SMOOTHING_S,
                    contact_speed: float = CONTACT_SPEED) -> np.ndarray:
    """The 269-dim features ``(T-1, 269)`` float32 of ``joints (T, 22, 3)`` world metres at ``fps``.

    Layout in the module docstring and :data:`FEATURE_SCHEMA`. ``facing_smoothing_s``: Gaussian
    sigma (s) of the root facing, 0 for none; ``contact_speed`` (m/s): a foot joint moving slower
    is in contact (the default equals HumanML3D's 0.002 m^2/frame at 20 fps).
    """
    fps = _check_fps(fps)
    world = check_joints(joints)
    if not np.isfinite(facing_smoothing_s) or facing_smoothing_s < 0:
        raise ValueError(f"facing_smoothing_s must be >= 0, got {facing_smoothing_s!r}")
    contact_speed = _check_fps(contact_speed, "contact_speed")
    canon, yaw0, t0 = canonicalize(world)
    psi = root_facing(world, fps, facing_smoothing_s) - yaw0  # canonical facing, psi(0) = 0
    n = len(canon) - 1
    root = canon[:, 0]
    out = np.zeros((n, FEATURE_DIM))
    out[:, 0] = -np.diff(psi) / 2.0
    out[:, 1:3] = _rotate_y(root[1:] - root[:-1], -psi[1:])[:, [0, 2]]
    out[:, 3] = root[:-1, 1]
    rel = canon[:-1, 1:] - root[:-1, None] * np.array([1.0, 0.0, 1.0])
    out[:, FeatureLayout.RIC] = _rotate_y(rel, -psi[:-1, None]).reshape(n, -1)
    out[:, FeatureLayout.ROTATIONS] = _to_6d(humanml3d_rotations(canon[:-1], psi[:-1])).reshape(n, -1)
    step = canon[1:] - canon[:-1]
    out[:, FeatureLayout.JOINT_VELOCITIES] = _rotate_y(step, -psi[:-1, None]).reshape(n, -1)
    sq = (step[:, list(FEET_LEFT + FEET_RIGHT)] ** 2).sum(-1)
    out[:, FeatureLayout.FOOT_CONTACTS] = sq < (contact_speed / fps) ** 2
    out[:, 263:269] = [np.sin(yaw0), np.cos(yaw0), t0[0], t0[1], t0[2], 0.0]
    return out.astype(np.float32)


def recover_joints(features, world: bool = True) -> np.ndarray:
    """Joint positions ``(N+1, 22, 3)`` float32 from features ``(N, 269)`` (or ``(N, 263)`` with
    ``world=False``).

    Integrates the root angular velocity to the facing (``psi(0) = 0``) and the rotated root velocity
    to the root XZ (starting at the origin), then rotates the ric positions back: frames 0..N-1,
    identical to HumanML3D's ``recover_from_ric``. Frame N is frame N-1 plus the last row's joint
    velocities, so ``recover_joints(motion_features(J)) == J`` for all ``T = N + 1`` frames.
    ``world=True`` maps the canonical result back with dims [263:269] of row 0:
    ``w = R_y(yaw0) c + t0``; ``world=False`` returns the canonical frame (floor y = 0).
    """
    f = np.asarray(features)
    if not world and f.ndim == 2 and f.shape[1] == HUMANML3D_DIM:
        f = _check_features(f, HUMANML3D_DIM)
    else:
        f = _check_features(f, FEATURE_DIM)
    n = len(f)
    psi = np.concatenate([[0.0], -2.0 * np.cumsum(f[:, 0])])  # (N+1,)
    vel = np.zeros((n, 3))
    vel[:, [0, 2]] = f[:, 1:3]
    root_xz = np.concatenate([np.zeros((1, 3)), np.cumsum(_rotate_y(vel, psi[1:]), axis=0)])
    out = np.empty((n + 1, NUM_JOINTS, 3))
    ric = f[:, FeatureLayout.RIC].reshape(n, NUM_JOINTS - 1, 3)
    out[:n, 1:] = _rotate_y(ric, psi[:n, None]) + root_xz[:n, None] * np.array([1.0, 0.0, 1.0])
    out[:n, 0] = root_xz[:n] * np.array([1.0, 0.0, 1.0])
    out[:n, 0, 1] = f[:, 3]
    step = f[-1, FeatureLayout.JOINT_VELOCITIES].reshape(NUM_JOINTS, 3)
    out[n] = out[n - 1] + _rotate_y(step, psi[n - 1])
    if world:
        sin0, cos0 = f[0, 263], f[0, 264]
        if np.hypot(sin0, cos0) < 1e-6:
            raise ValueError("features [263:265] (initial facing sin, cos) are zero: world transform unknown")
        yaw0 = np.arctan2(sin0, cos0)
        out = _rotate_y(out, yaw0) + f[0, 265:268]
    return out.astype(np.float32)


def resample_joints(joints, fps: float, target_fps: float) -> np.ndarray:
    """Linearly resample ``joints (T, 22, 3)`` from ``fps`` to ``target_fps`` (float64).

    Output frame ``k`` is at time ``k / target_fps`` s for every such time within the input's span
    ``(T - 1) / fps``; returns the input unchanged when the rates are equal.
    """
    fps, target_fps = _check_fps(fps), _check_fps(target_fps, "target_fps")
    j = check_joints(joints)
    if fps == target_fps:
        return j.copy()
    m = int(np.floor((len(j) - 1) / fps * target_fps + 1e-9)) + 1
    s = np.arange(m) * (fps / target_fps)
    i0 = np.minimum(np.floor(s).astype(int), len(j) - 2)
    w = (s - i0)[:, None, None]
    return (1.0 - w) * j[i0] + w * j[i0 + 1]


# ----------------------------------------------------------------------------------- statistics
_STD_GROUPS = ((0, 1), (1, 3), (3, 4), (4, 67), (67, 193), (193, 259), (259, 263), (263, 265), (265, 268), (268, 269))


def feature_stats(features_list, min_std: float = 1e-6) -> tuple[np.ndarray, np.ndarray]:
    """Normalisation statistics ``(mean (D,), std (D,))`` float32 over all rows of all sequences.

    ``features_list``: non-empty list of ``(N_i, D)`` arrays, D = 269 or 263. HumanML3D style: the
    mean is per dimension; each group's std (root angular velocity, root linear velocity, root height,
    ric, rotations, joint velocities, contacts, then initial facing, initial translation, spare) is
    replaced by the mean of its per-dimension stds, so a group is scaled as one. Any std still below
    ``min_std`` (a constant group, e.g. the spare dim) becomes 1, so ``(x - mean) / std`` stays finite.
    """
    if isinstance(features_list, np.ndarray) and features_list.ndim == 2:
        features_list = [features_list]
    if len(features_list) == 0:
        raise ValueError("feature_stats needs at least one feature array, got an empty list")
    first = np.asarray(features_list[0])
    dim = first.shape[1] if first.ndim == 2 else -1
    if dim not in (FEATURE_DIM, HUMANML3D_DIM):
        raise ValueError(f"features must have shape (N, 269) or (N, 263), got {first.shape}")
    data = np.concatenate([_check_features(f, dim, f"features[{i}]") for i, f in enumerate(features_list)])
    mean = data.mean(axis=0)
    std = data.std(axis=0)
    for a, b in _STD_GROUPS:
        if b <= dim:
            std[a:b] = std[a:b].mean()
    std[std < min_std] = 1.0
    return mean.astype(np.float32), std.astype(np.float32)


# ------------------------------------------------------------------------------------- mirroring
def mirror_joints(joints) -> np.ndarray:
    """Left/right mirror of ``joints (..., 22, 3)``: negate X, swap each left joint with its right twin.

    In the world frame this is the reflection in the plane x = 0.
    """
    j = np.array(joints, dtype=np.float64)
    if j.ndim < 2 or j.shape[-2:] != (NUM_JOINTS, 3):
        raise ValueError(f"joints must have shape (..., 22, 3), got {j.shape}")
    j = j[..., MIRROR_PERM, :]
    j[..., 0] *= -1.0
    return j


def mirror_features(features) -> np.ndarray:
    """Features ``(N, 269)`` (or 263) of the mirrored motion, float32:
    ``mirror_features(motion_features(J)) == motion_features(mirror_joints(J))``.

    Negates the angular velocity, the local x of velocities and positions, sin(yaw0) and t0_x;
    swaps left/right joints and contacts; a local rotation ``L`` becomes ``M L M`` (M = diag(-1, 1, 1)),
    i.e. 6D components 1, 2, 3 change sign.
    """
    f = np.asarray(features)
    f = _check_features(f, f.shape[1] if f.ndim == 2 and f.shape[1] == HUMANML3D_DIM else FEATURE_DIM).copy()
    n = len(f)
    f[:, 0] *= -1.0
    f[:, 1] *= -1.0
    perm21 = MIRROR_PERM[1:] - 1
    ric = f[:, FeatureLayout.RIC].reshape(n, 21, 3)[:, perm21]
    ric[..., 0] *= -1.0
    f[:, FeatureLayout.RIC] = ric.reshape(n, -1)
    rot = f[:, FeatureLayout.ROTATIONS].reshape(n, 21, 6)[:, perm21]
    rot[..., 1:4] *= -1.0
    f[:, FeatureLayout.ROTATIONS] = rot.reshape(n, -1)
    vel = f[:, FeatureLayout.JOINT_VELOCITIES].reshape(n, 22, 3)[:, MIRROR_PERM]
    vel[..., 0] *= -1.0
    f[:, FeatureLayout.JOINT_VELOCITIES] = vel.reshape(n, -1)
    f[:, FeatureLayout.FOOT_CONTACTS] = f[:, [261, 262, 259, 260]]
    if f.shape[1] == FEATURE_DIM:
        f[:, 263] *= -1.0
        f[:, 265] *= -1.0
    return f.astype(np.float32)


_TEXT_SWAPS = {"left": "right", "right": "left", "clockwise": "counterclockwise",
               "counterclockwise": "clockwise", "counter-clockwise": "clockwise",
               "anticlockwise": "clockwise", "anti-clockwise": "clockwise"}  # fmt: skip
_TEXT_RE = re.compile(
    r"(?<!\w)(?:(counter-?clockwise|anti-?clockwise|clockwise)|"
    r"(?<!all )(left|right)(?=(?:wards?|most|ward)?\b)(?! away\b| now\b))",
    re.IGNORECASE,
)


def _match_case(word: str, like: str) -> str:
    if like.isupper() and len(like) > 1:
        return word.upper()
    if like[0].isupper():
        return word[0].upper() + word[1:]
    return word


def mirror_text(text: str) -> str:
    """Swap left/right words for a mirrored motion, preserving case ("Left" -> "Right", "LEFT" ->
    "RIGHT", "leftward" -> "rightward", "left-handed" -> "right-handed", "rightmost" -> "leftmost"),
    and clockwise <-> counterclockwise. Words that only contain them ("leftover", "righteous",
    "bright") and the idioms "all right", "right away", "right now" are kept. The verb "left"
    ("he left the room") cannot be told apart and is swapped, as in InterGen's augmentation.
    """
    if not isinstance(text, str):
        raise ValueError(f"text must be a str, got {type(text).__name__}")

    def repl(m: re.Match) -> str:
        word = m.group(0)
        return _match_case(_TEXT_SWAPS[word.lower()], word)

    return _TEXT_RE.sub(repl, text)

"""InterGen / InterHuman 262-dim per-person features of a two-person motion, and their inverse.

Per person, ``T - 1`` rows at 30 fps (InterHuman's rate), in one shared canonical frame:

* ``[0:66]``    22 joint positions, m (HumanML3D joint order).
* ``[66:132]``  22 joint displacements t -> t+1, m/frame.
* ``[132:258]`` 21 local joint rotations (joints 1..21), 6D as InterHuman stores it (``rot_mat[..., :2]``
  flattened by row: :func:`rotations_6d_rows`), each relative to its parent and derived from the
  joint positions (:func:`dualhuman_builder.export.features.local_rotations`). InterHuman ships
  SMPL-H pose rotations relative to a T-pose rest there; ours have an arms-down rest and no bone
  twist (an approximation: InterGen's losses and mirroring use them, its joints come from [0:66]).
* ``[258:262]`` foot contacts (left ankle, left foot, right ankle, right foot): squared displacement
  t -> t+1 below ``(contact_speed / fps)^2`` (InterGen: 0.001 m^2 at 30 fps) and height at t below
  0.12 m (ankles) / 0.05 m (feet).

The shared frame is person 1's canonical frame: floor at person 1's lowest joint height, person 1's
root XZ of frame 0 at the origin, person 1 facing +Z at frame 0 (facing from the hips only, as
InterGen). The SAME rigid transform is applied to person 2, so person 2 is expressed relative to
person 1 (InterGen floors each person separately and then re-applies the relative yaw and XZ
offset; one transform keeps the relative height too). :class:`PairTransform` maps back to the world.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import NamedTuple

import numpy as np

from dualhuman_builder.export.features import (
    FEATURE_FIELDS,
    FEET_LEFT,
    FEET_RIGHT,
    NUM_JOINTS,
    FeatureField,
    _check_features,
    _check_fps,
    _rotate_y,
    check_joints,
    facing_yaw,
    local_rotations,
    resample_joints,
    root_facing,
)

INTERHUMAN_DIM = 262
INTERHUMAN_FPS = 30.0
#: InterGen's contact threshold, squared metres per frame at 30 fps, and the speed it amounts to.
INTERGEN_CONTACT_THRESHOLD = 0.001
INTERHUMAN_CONTACT_SPEED = float(np.sqrt(INTERGEN_CONTACT_THRESHOLD) * INTERHUMAN_FPS)  # ~0.949 m/s
#: Height limits (m) for contact of the ankle and foot joints (InterGen's ``heightfactor``).
CONTACT_HEIGHTS = (0.12, 0.05)
#: Hips (right, left) defining the facing for the shared frame (InterGen uses the hips only).
HIP_JOINTS = (2, 1)

INTERHUMAN_FIELDS: tuple[FeatureField, ...] = (
    FeatureField("positions", 0, 66, (22, 3), "m", "joint positions at frame t in person 1's canonical frame"),
    FeatureField("velocities", 66, 132, (22, 3), "m/frame", "joint displacements t -> t+1, same frame"),
    FeatureField("rotations_6d", 132, 258, (21, 6), "1", dict((f.name, f.meaning) for f in FEATURE_FIELDS)["rotations_6d"]),
    FeatureField("foot_contacts", 258, 262, (4,), "0/1",
                 "left ankle, left foot, right ankle, right foot: slower than contact_speed and below "
                 "0.12 m (ankles) / 0.05 m (feet)"),
)  # fmt: skip
INTERHUMAN_SCHEMA: list[dict] = [{**asdict(f), "shape": list(f.shape)} for f in INTERHUMAN_FIELDS]


@dataclass(frozen=True)
class PairTransform:
    """Rigid map between the world and the shared canonical frame.

    ``canonical = R_y(-yaw0) (world - translation)``; ``yaw0`` radians (person 1's facing at frame 0,
    0 = +Z), ``translation (3,)`` world metres = (person 1 root x at frame 0, person 1 floor height,
    person 1 root z at frame 0).
    """

    yaw0: float
    translation: tuple[float, float, float]

    def to_canonical(self, points) -> np.ndarray:
        """World points ``(..., 3)`` -> canonical, float64."""
        return _rotate_y(np.asarray(points, dtype=np.float64) - np.asarray(self.translation), -self.yaw0)

    def to_world(self, points) -> np.ndarray:
        """Canonical points ``(..., 3)`` -> world, float64."""
        return _rotate_y(np.asarray(points, dtype=np.float64), self.yaw0) + np.asarray(self.translation)


class InterHumanFeatures(NamedTuple):
    """``person1``, ``person2``: ``(T'-1, 262)`` float32 at ``fps``; ``transform``: world <-> shared frame."""

    person1: np.ndarray
    person2: np.ndarray
    transform: PairTransform
    fps: float


def pair_transform(joints_a) -> PairTransform:
    """The shared frame defined by person 1's ``joints_a (T, 22, 3)`` world metres."""
    a = check_joints(joints_a, "joints_a", min_frames=1)
    yaw0 = float(facing_yaw(a[:1], HIP_JOINTS)[0])
    return PairTransform(yaw0, (float(a[0, 0, 0]), float(a[..., 1].min()), float(a[0, 0, 2])))


def canonicalize_pair(joints_a, joints_b) -> tuple[np.ndarray, np.ndarray, PairTransform]:
    """Both persons ``(T, 22, 3)`` in person 1's canonical frame (float64), and the transform."""
    a = check_joints(joints_a, "joints_a", min_frames=1)
    b = check_joints(joints_b, "joints_b", min_frames=1)
    if a.shape != b.shape:
        raise ValueError(f"joints_a and joints_b must have the same shape, got {a.shape} and {b.shape}")
    tr = pair_transform(a)
    return tr.to_canonical(a), tr.to_canonical(b), tr


def rotations_6d_rows(mats: np.ndarray) -> np.ndarray:
    """InterHuman's 6D of rotation matrices ``(..., 3, 3)``: ``mats[..., :2]`` flattened by row,
    ``[r00, r01, r10, r11, r20, r21]`` (``(..., 6)``), the layout InterGen's mirroring negates at 1, 2, 4."""
    m = np.asarray(mats)
    return m[..., :2].reshape(m.shape[:-2] + (6,))


def rotations_from_6d_rows(d6: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` of InterHuman 6D ``(..., 6)`` (inverse of :func:`rotations_6d_rows`;
    the two columns are Gram-Schmidt orthonormalised, the third is their cross product)."""
    cols = np.asarray(d6, dtype=np.float64).reshape(np.shape(d6)[:-1] + (3, 2))
    x = cols[..., 0] / np.linalg.norm(cols[..., 0], axis=-1, keepdims=True)
    y = cols[..., 1] - (x * cols[..., 1]).sum(-1, keepdims=True) * x
    y = y / np.linalg.norm(y, axis=-1, keepdims=True)
    return np.stack([x, y, np.cross(x, y)], axis=-1)


def _person_features(c: np.ndarray, fps: float, contact_speed: float) -> np.ndarray:
    n = len(c) - 1
    out = np.zeros((n, INTERHUMAN_DIM))
    out[:, 0:66] = c[:-1].reshape(n, -1)
    step = c[1:] - c[:-1]
    out[:, 66:132] = step.reshape(n, -1)
    out[:, 132:258] = rotations_6d_rows(local_rotations(c[:-1], root_facing(c, fps)[:-1])).reshape(n, -1)
    feet = list(FEET_LEFT + FEET_RIGHT)
    slow = (step[:, feet] ** 2).sum(-1) < (contact_speed / fps) ** 2
    low = c[:-1, feet, 1] < np.array(CONTACT_HEIGHTS * 2)
    out[:, 258:262] = slow & low
    return out.astype(np.float32)


def interhuman_features(joints_a, joints_b, fps: float, target_fps: float | None = INTERHUMAN_FPS,
                        contact_speed: float = INTERHUMAN_CONTACT_SPEED) -> InterHumanFeatures:
    """InterHuman 262-dim features of two persons ``(T, 22, 3)`` world metres sampled at ``fps``.

    Both are first resampled linearly to ``target_fps`` (None keeps ``fps``), then put in person 1's
    canonical frame (module docstring). Returns ``(person1, person2, transform, fps)`` with
    ``(T'-1, 262)`` float32 features, ``T'`` the resampled frame count (at least 2 needed).
    """
    fps = _check_fps(fps)
    a = check_joints(joints_a, "joints_a")
    b = check_joints(joints_b, "joints_b")
    if a.shape != b.shape:
        raise ValueError(f"joints_a and joints_b must have the same shape, got {a.shape} and {b.shape}")
    contact_speed = _check_fps(contact_speed, "contact_speed")
    if target_fps is not None:
        a, b = resample_joints(a, fps, target_fps), resample_joints(b, fps, target_fps)
        fps = float(target_fps)
        if len(a) < 2:
            raise ValueError(f"fewer than 2 frames at {fps} fps: the motion is too short")
    ca, cb, tr = canonicalize_pair(a, b)
    return InterHumanFeatures(_person_features(ca, fps, contact_speed), _person_features(cb, fps, contact_speed), tr, fps)


def recover_interhuman(features, transform: PairTransform | None = None) -> np.ndarray:
    """Joint positions ``(N+1, 22, 3)`` float32 from one person's ``(N, 262)`` features.

    Frames 0..N-1 are the stored positions, frame N = frame N-1 + the last row's displacement, so all
    ``T'`` frames come back. Shared canonical frame, or the world if ``transform`` is given.
    """
    f = _check_features(features, INTERHUMAN_DIM)
    n = len(f)
    out = np.empty((n + 1, NUM_JOINTS, 3))
    out[:n] = f[:, 0:66].reshape(n, NUM_JOINTS, 3)
    out[n] = out[n - 1] + f[-1, 66:132].reshape(NUM_JOINTS, 3)
    if transform is not None:
        out = transform.to_world(out)
    return out.astype(np.float32)

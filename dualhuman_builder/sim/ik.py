"""Inverse kinematics on anny's skeleton, vectorised over frames (numpy, float64).

Limbs are solved in closed form (two-bone IK): the middle joint (elbow, knee) lies in the plane
of the limb root, the target and a *pole* direction, and each segment's world-aligned global
rotation maps its rest frame — (segment direction, hinge axis) — onto the solved one. Since both
segments of a limb share the solved hinge axis, the middle joint's local rotation is a pure hinge
flexion about its rest hinge axis, as anatomy wants. End effectors (hand, foot) get a global
orientation; for the hand the twist about the forearm goes to the forearm's twist bone
(``lowerarm02``), so the wrist bends but does not twist.

Shapes: ``(T, 3)`` points and directions, ``(T, 3, 3)`` rotations; all in world metres.
"""

from __future__ import annotations

import numpy as np

from dualhuman_builder.sim.skeleton import Skeleton


def normalize(v: np.ndarray, eps: float = 1e-12) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), eps)


def frame(direction: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Orthonormal frames ``(..., 3, 3)`` with columns (direction, normal orthogonalised, their cross)."""
    d = normalize(direction)
    n = normalize(normal - (normal * d).sum(-1, keepdims=True) * d)
    return np.stack([d, n, np.cross(d, n)], axis=-1)


def map_frames(d0: np.ndarray, n0: np.ndarray, d1: np.ndarray, n1: np.ndarray) -> np.ndarray:
    """Rotation taking direction ``d0`` to ``d1`` and normal ``n0`` to ``n1`` (orthogonalised)."""
    return frame(d1, n1) @ np.swapaxes(frame(d0, n0), -1, -2)


def rot_y(angle: np.ndarray) -> np.ndarray:
    """Rotations ``(..., 3, 3)`` about the world up axis (+Y) by ``angle`` radians."""
    c, s = np.cos(angle), np.sin(angle)
    z, o = np.zeros_like(angle), np.ones_like(angle)
    return np.stack([np.stack([c, z, s], -1), np.stack([z, o, z], -1), np.stack([-s, z, c], -1)], -2)


def axis_angle(axis: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """Rotation matrices from unit axes ``(..., 3)`` and angles ``(...)`` (Rodrigues)."""
    axis = normalize(np.broadcast_to(axis, np.shape(angle) + (3,)))
    x, y, z = axis[..., 0], axis[..., 1], axis[..., 2]
    c, s = np.cos(angle), np.sin(angle)
    C = 1 - c
    return np.stack([
        np.stack([c + x * x * C, x * y * C - z * s, x * z * C + y * s], -1),
        np.stack([y * x * C + z * s, c + y * y * C, y * z * C - x * s], -1),
        np.stack([z * x * C - y * s, z * y * C + x * s, c + z * z * C], -1),
    ], -2)  # fmt: skip


def rotation_angle(R: np.ndarray) -> np.ndarray:
    """Angle (radians) of rotations ``(..., 3, 3)``."""
    return np.arccos(np.clip((np.trace(R, axis1=-2, axis2=-1) - 1) / 2, -1.0, 1.0))


def twist_angle(R: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """Angle (radians) of the twist of rotations ``R (..., 3, 3)`` about ``axis`` in the
    swing-twist decomposition (the twist is unique; the remainder is a pure swing)."""
    from scipy.spatial.transform import Rotation

    q = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_quat().reshape(R.shape[:-2] + (4,))  # xyzw
    q = np.where(q[..., 3:] < 0, -q, q)  # w >= 0: angles in (-pi, pi]
    a = normalize(np.asarray(axis, dtype=np.float64))
    return 2.0 * np.arctan2((q[..., :3] * a).sum(-1), q[..., 3])


class LimbChain:
    """A two-bone limb of ``skeleton``: ``upper`` -> ``lower`` -> ``end`` bones (e.g. upperarm01.L,
    lowerarm01.L, wrist.L); ``twist`` optionally names the forearm twist bone between lower and end."""

    def __init__(self, skeleton: Skeleton, upper: str, lower: str, end: str, twist: str | None = None):
        sk = self.sk = skeleton
        self.iu, self.il, self.ie = sk.index(upper), sk.index(lower), sk.index(end)
        self.it = sk.index(twist) if twist else None
        self.parent_u = int(sk.parents[self.iu])
        r = sk.rest
        self.u0 = r[self.il] - r[self.iu]
        self.f0 = r[self.ie] - r[self.il]
        self.l1, self.l2 = float(np.linalg.norm(self.u0)), float(np.linalg.norm(self.f0))
        self.n0 = normalize(np.cross(self.u0, self.f0))  # rest hinge axis

    @property
    def reach(self) -> float:
        return self.l1 + self.l2

    def solve(self, local: np.ndarray, transl: np.ndarray, target: np.ndarray, pole: np.ndarray,
              end_rotation: np.ndarray | None = None, max_extension: float = 0.995,
              max_twist: float = np.radians(85.0), max_swing: float = np.radians(70.0),
              fallback_pole: np.ndarray | None = None, swivel: np.ndarray | None = None):  # fmt: skip
        """Set ``local`` (in place) so the end bone's head reaches ``target (T, 3)`` with the middle
        joint towards ``pole (T, 3)`` (a direction), and optionally the end bone's world-aligned
        global rotation to ``end_rotation (T, 3, 3)``. Targets beyond ``max_extension`` of the
        reach are pulled in along the line. With a twist bone, the end's rotation relative to the
        lower segment is limited to ``max_twist`` about the segment (forearm pronation/supination)
        and ``max_swing`` of bend (wrist flexion/deviation), anatomical ranges; the nearest
        reachable orientation is used. Where ``pole`` nearly lines up with the limb, the middle
        joint turns towards ``fallback_pole`` instead (smoothly), so the bend plane never flips.
        ``swivel (T,)`` (radians) then turns the middle joint about the root-to-target axis.
        Returns the reached end positions ``(T, 3)`` and the end's achieved global rotations
        ``(T, 3, 3)`` (None without ``end_rotation``)."""
        heads, glob = self.sk.fk(local, transl)
        S = heads[:, self.iu]
        to_t = target - S
        d = np.linalg.norm(to_t, axis=-1)
        n = to_t / np.maximum(d, 1e-9)[:, None]
        d = np.clip(d, abs(self.l1 - self.l2) + 1e-4, max_extension * self.reach)
        p = pole - (pole * n).sum(-1, keepdims=True) * n
        if fallback_pole is not None:
            weak = np.clip((0.4 - np.linalg.norm(p, axis=-1)) / 0.4, 0.0, 1.0)[:, None]
            q = fallback_pole - (fallback_pole * n).sum(-1, keepdims=True) * n
            p = (1 - weak) * normalize(p) + weak * normalize(q)
        p = normalize(p)
        if swivel is not None:
            p = np.einsum("tij,tj->ti", axis_angle(n, np.asarray(swivel, dtype=np.float64)), p)
        a = (self.l1**2 - self.l2**2 + d**2) / (2 * d)
        b = np.sqrt(np.maximum(self.l1**2 - a**2, 0.0))
        E = S + a[:, None] * n + b[:, None] * p
        T = S + d[:, None] * n
        hinge = normalize(np.cross(p, n))
        A_u = map_frames(self.u0, self.n0, E - S, hinge)
        A_l = map_frames(self.f0, self.n0, T - E, hinge)
        local[:, self.iu] = np.swapaxes(glob[:, self.parent_u], -1, -2) @ A_u
        for c in _between(self.sk.parents, self.iu, self.il):
            local[:, c] = np.eye(3)  # twist bones of the upper segment follow it
        local[:, self.il] = np.swapaxes(A_u, -1, -2) @ A_l  # its parent (a twist bone or upper) has global A_u
        for c in _between(self.sk.parents, self.il, self.ie):
            local[:, c] = np.eye(3)
        if end_rotation is None:
            return T, None
        rel = np.swapaxes(A_l, -1, -2) @ end_rotation  # end relative to the lower segment
        if self.it is None:
            local[:, self.ie] = rel
            return T, end_rotation
        axis = normalize(self.f0)
        angle = twist_angle(rel, axis)
        tw = axis_angle(axis, np.clip(angle, -max_twist, max_twist))
        swing = np.swapaxes(axis_angle(axis, angle), -1, -2) @ rel  # rel = twist @ swing
        s_angle = rotation_angle(swing)
        scale = np.where(s_angle > max_swing, max_swing / np.maximum(s_angle, 1e-12), 1.0)
        swing = _scale_rotation(swing, scale)
        local[:, self.it] = tw
        local[:, self.ie] = swing
        return T, A_l @ tw @ swing


def _scale_rotation(R: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Rotations with the same axes as ``R (..., 3, 3)`` and their angles times ``scale (...)``."""
    from scipy.spatial.transform import Rotation

    rv = Rotation.from_matrix(R.reshape(-1, 3, 3)).as_rotvec().reshape(R.shape[:-1])
    return Rotation.from_rotvec((rv * scale[..., None]).reshape(-1, 3)).as_matrix().reshape(R.shape)


def _between(parents: np.ndarray, ancestor: int, descendant: int) -> list[int]:
    """Bones strictly between ``ancestor`` and ``descendant`` on the parent chain."""
    out = []
    c = int(parents[descendant])
    while c != ancestor and c >= 0:
        out.append(c)
        c = int(parents[c])
    return out

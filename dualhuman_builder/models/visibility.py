"""Per-joint visibility of two people, for every frame, from a ring of virtual cameras around the pair.

The reaction prior's noise augmentation makes occluded joints noisier, as an image-based estimator's
errors are; the paper estimates per-joint visibility probabilities from a ring of virtual cameras.
Here the probability is the share of the ring's cameras that see the joint, computed from the
bodies themselves, so every frame has it (not only rendered ones).

**The ring**: ``cameras`` cameras evenly spaced in azimuth (the first on the +X side of the pair)
on a horizontal circle of ``radius`` metres around the pair's midpoint (the mean of the two pelvis
joints in X and Z, per frame: the ring follows the pair), ``height`` metres above the floor (y = 0),
each pointing at the midpoint. Each camera's field of view is taken to cover both people; at the
default 4 m a 60-degree lens covers 4.6 m across the midpoint.

**Occlusion**: a joint is hidden from a camera when the segment from the camera centre to the joint
passes through a body capsule of either person (:data:`CAPSULES`: a segment between two joints and a
radius, 24 per person, documented radii of an adult body). A capsule that already contains the joint
(the flesh around it: the bones that meet at the joint, the torso around a spine joint) does not
hide that joint from anyone; a joint inside the *other* person's body (interpenetration) is hidden.
Capsules are a coarse stand-in for the mesh: what matters for the noise model is which joints are
behind a body from most views, not the exact silhouette edge.

Vectorised numpy, in chunks of frames to bound memory (about 40 MB a chunk at the defaults): a bounding-sphere
test of every (camera, joint, capsule) triple, then the exact segment distance for the few that pass it.
"""

from __future__ import annotations

import numpy as np

from dualhuman_builder.errors import DualhumanError

#: Joints per person (HumanML3D's 22, :data:`~dualhuman_builder.body.joints.JOINT22_NAMES` order).
NUM_JOINTS = 22
#: Body capsules (joint i, joint j, radius in metres) over the 22 joints: spine and torso, pelvis,
#: legs, shoulders and arms, neck and head. Radii of an average adult: torso 0.13 m half-depth,
#: thigh 0.08, shin 0.055, upper arm 0.05, forearm 0.04, head 0.10.
CAPSULES = (
    (0, 3, 0.12), (3, 6, 0.13), (6, 9, 0.13), (9, 12, 0.09),  # pelvis -> spine1 -> spine2 -> spine3 -> neck
    (12, 15, 0.10),  # neck -> head
    (0, 1, 0.10), (0, 2, 0.10),  # pelvis girdle
    (16, 17, 0.07),  # shoulder girdle (upper chest width)
    (1, 16, 0.05), (2, 17, 0.05),  # torso sides, hip to shoulder: with the spine, a torso 0.4 m wide
    (1, 4, 0.08), (2, 5, 0.08), (4, 7, 0.055), (5, 8, 0.055), (7, 10, 0.04), (8, 11, 0.04),  # legs, feet
    (9, 13, 0.06), (9, 14, 0.06), (13, 16, 0.05), (14, 17, 0.05),  # collars, shoulders
    (16, 18, 0.05), (17, 19, 0.05), (18, 20, 0.04), (19, 21, 0.04),  # upper arms, forearms
)  # fmt: skip
_CAP_I = np.array([c[0] for c in CAPSULES])
_CAP_J = np.array([c[1] for c in CAPSULES])
_CAP_R = np.array([c[2] for c in CAPSULES])
#: Frames per chunk of the vectorised test (bounds the temporary arrays).
CHUNK_FRAMES = 64


def ring_cameras(joints_a: np.ndarray, joints_b: np.ndarray, cameras: int = 8, radius: float = 4.0,
                 height: float = 1.6) -> np.ndarray:  # fmt: skip
    """Camera centres ``(T, cameras, 3)`` in metres: the ring of the module docstring around the
    pair's midpoint (mean pelvis X and Z of ``joints_a``, ``joints_b`` ``(T, 22, 3)``) at ``height``."""
    mid = 0.5 * (np.asarray(joints_a)[:, 0] + np.asarray(joints_b)[:, 0])  # (T, 3)
    ang = 2.0 * np.pi * np.arange(cameras) / cameras
    ring = np.stack([radius * np.cos(ang), np.zeros(cameras), radius * np.sin(ang)], axis=1)  # (C, 3)
    centre = np.stack([mid[:, 0], np.full(len(mid), float(height)), mid[:, 2]], axis=1)
    return centre[:, None, :] + ring[None]


def _segment_distance2(a, b, c, e, f, rr) -> np.ndarray:
    """Squared smallest distance between segments ``p1 + s d1`` and ``p2 + t d2`` (s, t in [0, 1]) from
    their dot products: ``a = d1.d1``, ``b = d1.d2``, ``c = d1.r``, ``e = d2.d2``, ``f = d2.r``,
    ``rr = r.r`` with ``r = p1 - p2`` (broadcast arrays). The clamped closest-point solution of
    Ericson's Real-Time Collision Detection 5.1.9, on scalars only, so that the many pairs need no 3-vectors."""
    a_safe, e_safe = np.maximum(a, 1e-12), np.maximum(e, 1e-12)
    denom = a * e - b * b
    s = np.where(denom > 1e-12 * a * e, np.clip((b * f - c * e) / np.maximum(denom, 1e-30), 0.0, 1.0), 0.0)
    t = (b * s + f) / e_safe
    s = np.where(t < 0.0, np.clip(-c / a_safe, 0.0, 1.0), np.where(t > 1.0, np.clip((b - c) / a_safe, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    return np.maximum(rr + s * s * a + t * t * e + 2.0 * s * c - 2.0 * t * f - 2.0 * s * t * b, 0.0)


def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("...k,...k->...", x, y)


def _point_segment_distance(p, q0, q1) -> np.ndarray:
    d = q1 - q0
    t = np.clip(np.einsum("...k,...k->...", p - q0, d) / np.maximum(np.einsum("...k,...k->...", d, d), 1e-12), 0.0, 1.0)
    diff = p - (q0 + t[..., None] * d)
    return np.sqrt(np.einsum("...k,...k->...", diff, diff))


def _check(name: str, x) -> np.ndarray:
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 3 or x.shape[1:] != (NUM_JOINTS, 3):
        raise DualhumanError(f"{name} must have shape (T, {NUM_JOINTS}, 3), got {x.shape}",
                             fix="pass the 22 joints of each frame in metres (an export's a.joints / b.joints)")  # fmt: skip
    if not np.isfinite(x).all():
        raise DualhumanError(f"{name} holds NaN or inf", fix="pass finite joint positions")
    return x


def joint_visibility(joints_a, joints_b, cameras: int = 8, radius: float = 4.0, height: float = 1.6,
                     radius_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Share of the ring's cameras that see each joint of each person, every frame.

    ``joints_a``, ``joints_b``: ``(T, 22, 3)`` metres, Y up (an export's ``a.joints``/``b.joints``).
    ``cameras``, ``radius`` (m), ``height`` (m): the ring (module docstring). ``radius_scale``
    multiplies every capsule radius (:data:`CAPSULES`). Returns ``(vis_a, vis_b)``, float32
    ``(T, 22)`` in [0, 1]: 1 seen by every camera, 0 hidden from all.
    """
    ja, jb = _check("joints_a", joints_a), _check("joints_b", joints_b)
    if ja.shape != jb.shape:
        raise DualhumanError(f"joints_a {ja.shape} and joints_b {jb.shape} differ in length", fix="pass the same frames of both people")
    if not (isinstance(cameras, (int, np.integer)) and cameras >= 1) or not radius > 0 or not radius_scale > 0:
        raise DualhumanError(f"bad camera ring: cameras={cameras!r}, radius={radius!r}, radius_scale={radius_scale!r}",
                             fix="use at least one camera, a positive radius and a positive radius_scale")  # fmt: skip
    T = ja.shape[0]
    cams = ring_cameras(ja, jb, int(cameras), float(radius), float(height))  # (T, C, 3)
    radii = np.concatenate([_CAP_R, _CAP_R]) * float(radius_scale)  # (K,) capsules of a, then of b
    owner = np.repeat([0, 1], len(CAPSULES))  # (K,)
    seen = np.zeros((T, 2 * NUM_JOINTS), dtype=np.float64)
    for lo in range(0, T, CHUNK_FRAMES):
        hi = min(T, lo + CHUNK_FRAMES)
        both = np.concatenate([ja[lo:hi], jb[lo:hi]], axis=1)  # (F, 2J, 3): the targets
        q0 = np.concatenate([ja[lo:hi, _CAP_I], jb[lo:hi, _CAP_I]], axis=1)  # (F, K, 3)
        q1 = np.concatenate([ja[lo:hi, _CAP_J], jb[lo:hi, _CAP_J]], axis=1)
        # a capsule of the joint's own body that contains it is its own flesh: it hides nothing of it
        inside = _point_segment_distance(both[:, :, None], q0[:, None], q1[:, None]) < radii  # (F, 2J, K)
        own = (np.repeat([0, 1], NUM_JOINTS)[:, None] == owner[None, :])[None]  # (1, 2J, K)
        counts = ~(inside & own)
        cam = cams[lo:hi]  # (F, C, 3)
        d1 = both[:, None] - cam[:, :, None]  # (F, C, 2J, 3): camera -> joint
        a = np.einsum("fcjx,fcjx->fcj", d1, d1)[..., None]  # (F, C, 2J, 1)
        # broad phase: the capsule's bounding sphere (centre, half length + radius) against the ray
        centre, half = 0.5 * (q0 + q1), 0.5 * np.linalg.norm(q1 - q0, axis=-1) + radii  # (F, K, 3), (F, K)
        to_c = centre[:, None] - cam[:, :, None]  # (F, C, K, 3)
        u = np.matmul(d1, to_c.transpose(0, 1, 3, 2))  # (F, C, 2J, K): d1 . (centre - camera)
        t = np.clip(u / np.maximum(a, 1e-12), 0.0, 1.0)
        near = np.einsum("fckx,fckx->fck", to_c, to_c)[:, :, None] - 2.0 * t * u + t * t * a < (half**2)[:, None, None]
        f_, c_, j_, k_ = np.nonzero(near & counts[:, None])
        hit = np.zeros(near.shape, dtype=bool)
        if len(f_):  # narrow phase on the candidates only
            v1, p2, v2 = d1[f_, c_, j_], q0[f_, k_], (q1 - q0)[f_, k_]
            r = cam[f_, c_] - p2
            dist2 = _segment_distance2(_dot(v1, v1), _dot(v1, v2), _dot(v1, r), _dot(v2, v2), _dot(v2, r), _dot(r, r))
            hit[f_, c_, j_, k_] = dist2 < radii[k_] ** 2
        hidden = hit.any(axis=-1)  # (F, C, 2J)
        seen[lo:hi] = 1.0 - hidden.mean(axis=1)
    seen = seen.astype(np.float32)
    return seen[:, :NUM_JOINTS], seen[:, NUM_JOINTS:]

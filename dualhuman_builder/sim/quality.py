"""Measures of a two-person motion's physical plausibility, which hold generated scenes to their
contract: interpenetration, foot sliding, anatomical joint limits.

All distances in metres, angles in degrees.
"""

from __future__ import annotations

import functools

import numpy as np

#: Anatomical ranges of motion (degrees) of each bone the scenes move, relative to its parent,
#: measured from anny's rest pose as ``(swing, twist)``: ``twist`` is the rotation about the bone's
#: own axis (rest head towards its first child), ``swing`` the rest. Generous ranges from the
#: AAOS / Norkin & White goniometry tables: shoulder elevation to 180 and humeral rotation 160 in
#: all (70 internal, 90 external from anatomical neutral; anny's A-pose holds the humerus turned
#: inwards from neutral, so up to 115 away from it);
#: elbow flexion 150 (no twist: pronation lives in the forearm's twist bone, up to 90); wrist
#: flexion/extension 80; hip flexion 125 and rotation 45; knee flexion 140; ankle 50 with 35 of
#: tibial rotation; about 20 per spine segment and 45 for the neck and head. ``None``: no limit.
JOINT_LIMITS_DEG = {
    **{b: (20, 20) for b in ("spine05", "spine04", "spine03", "spine02", "spine01")},
    "neck01": (45, 45), "head": (45, 45),
    "clavicle.L": (30, 30), "clavicle.R": (30, 30),
    "upperarm01.L": (None, 115), "upperarm01.R": (None, 115),
    "lowerarm01.L": (150, 25), "lowerarm01.R": (150, 25),
    "lowerarm02.L": (15, 90), "lowerarm02.R": (15, 90),
    "wrist.L": (80, 25), "wrist.R": (80, 25),
    "upperleg01.L": (125, 45), "upperleg01.R": (125, 45),
    "lowerleg01.L": (140, 30), "lowerleg01.R": (140, 30),
    "foot.L": (50, 35), "foot.R": (50, 35),
}  # fmt: skip

#: The axis each bone's twist is measured about, as (from bone, to bone) rest heads: a limb's
#: own direction, except the wrist (the forearm: pronation is not the wrist's) and the foot (the
#: shank: turning the foot about the vertical is tibial rotation).
TWIST_AXES = {
    "spine05": ("spine05", "spine04"), "spine04": ("spine04", "spine03"), "spine03": ("spine03", "spine02"),
    "spine02": ("spine02", "spine01"), "spine01": ("spine01", "neck01"), "neck01": ("neck01", "head"),
    "head": ("neck01", "head"),
    **{f"clavicle.{s}": (f"clavicle.{s}", f"upperarm01.{s}") for s in "LR"},
    **{f"upperarm01.{s}": (f"upperarm01.{s}", f"lowerarm01.{s}") for s in "LR"},
    **{f"lowerarm01.{s}": (f"lowerarm01.{s}", f"wrist.{s}") for s in "LR"},
    **{f"lowerarm02.{s}": (f"lowerarm01.{s}", f"wrist.{s}") for s in "LR"},
    **{f"wrist.{s}": (f"lowerarm01.{s}", f"wrist.{s}") for s in "LR"},
    **{f"upperleg01.{s}": (f"upperleg01.{s}", f"lowerleg01.{s}") for s in "LR"},
    **{f"lowerleg01.{s}": (f"lowerleg01.{s}", f"foot.{s}") for s in "LR"},
    **{f"foot.{s}": (f"lowerleg01.{s}", f"foot.{s}") for s in "LR"},
}  # fmt: skip
#: Humeral rotation measured by swing-twist from the rest pose stops meaning anatomical rotation
#: once the arm is raised far (the same raised arm is reached with different "twists" along
#: different paths: Codman's paradox): the shoulder's twist is only checked below this swing.
SHOULDER_TWIST_CHECKED_BELOW_SWING = 90.0

#: Hinge joints (bone -> (upper bone, end bone)): they may flex, but not bend backwards by more
#: than :data:`HYPEREXTENSION_DEG` (signed about their rest hinge axis, where anny's rest pose is
#: slightly flexed).
HINGES = {
    "lowerarm01.L": ("upperarm01.L", "wrist.L"), "lowerarm01.R": ("upperarm01.R", "wrist.R"),
    "lowerleg01.L": ("upperleg01.L", "foot.L"), "lowerleg01.R": ("upperleg01.R", "foot.R"),
}  # fmt: skip
HYPEREXTENSION_DEG = 10.0


def penetration_depth(distances: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Per-frame depth (m, >= 0) of the deepest vertex of either body inside the other."""
    worst = [np.nan_to_num(-d.astype(np.float32), nan=0.0).max(axis=1) for d in distances]
    return np.maximum(np.maximum(worst[0], worst[1]), 0.0)


def foot_sliding(track, stance: dict[str, np.ndarray]) -> float:
    """Largest per-frame horizontal+vertical displacement (m) of a planted foot's ankle or ball
    (the foot and middle-toe bone heads) between consecutive frames that are both in stance."""
    heads = track.bone_heads()
    names = track.bone_names
    worst = 0.0
    for side, mask in stance.items():
        both = mask[1:] & mask[:-1]
        if not both.any():
            continue
        for bone in (f"foot.{side}", f"toe3-1.{side}"):
            p = heads[:, names.index(bone)]
            step = np.linalg.norm(np.diff(p, axis=0), axis=1)
            worst = max(worst, float(step[both].max()))
    return worst


def joint_limit_violations(track) -> dict[str, float]:
    """Bones beyond :data:`JOINT_LIMITS_DEG` (``"<bone> swing"`` / ``"<bone> twist"`` -> worst
    angle, degrees), plus hinge joints bent backwards (``"<bone> hyperextension"``)."""
    import roma
    import torch

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.sim.ik import axis_angle, normalize, rotation_angle, twist_angle

    R = roma.rotvec_to_rotmat(torch.tensor(np.array(track.pose), dtype=torch.float64)).numpy()
    model = get_body_model()
    with torch.no_grad():
        rest = model.rest(model.shape_tensor(np.array(track.shape))).bone_heads[0].double().numpy()
    names = track.bone_names
    out = {}
    for bone, (max_swing, max_twist) in JOINT_LIMITS_DEG.items():
        i = names.index(bone)
        a, b = TWIST_AXES[bone]
        axis = normalize(rest[names.index(b)] - rest[names.index(a)])
        twist = twist_angle(R[:, i], axis)
        swing = rotation_angle(R[:, i] @ np.swapaxes(axis_angle(axis, twist), -1, -2))
        if bone.startswith("upperarm"):
            twist = np.where(np.degrees(swing) < SHOULDER_TWIST_CHECKED_BELOW_SWING, twist, 0.0)
        worst_twist, worst_swing = np.degrees(np.abs(twist).max()), np.degrees(swing.max())
        if max_twist is not None and worst_twist > max_twist:
            out[f"{bone} twist"] = float(worst_twist)
        if max_swing is not None and worst_swing > max_swing:
            out[f"{bone} swing"] = float(worst_swing)
    for bone, (upper, end) in HINGES.items():
        i_u, i_m, i_e = (track.bone_names.index(b) for b in (upper, bone, end))
        u0, f0 = rest[i_m] - rest[i_u], rest[i_e] - rest[i_m]
        axis = np.cross(u0, f0)
        rest_bend = np.degrees(np.arctan2(np.linalg.norm(axis), u0 @ f0))
        bend = rest_bend + np.degrees(twist_angle(R[:, i_m], axis))
        back = float(-bend.min())
        if back > HYPEREXTENSION_DEG:
            out[f"{bone} hyperextension"] = back
    return out


# ------------------------------------------------------------------ inside/outside by winding number
#: Frames per call of the winding-number penetration query (bounds its pool of meshes).
WINDING_CHUNK = 16


@functools.lru_cache(maxsize=1)
def _winding_term():
    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.geometry.collision import CollisionTerm

    return CollisionTerm(get_body_model().faces, sign="winding")


def winding_depths(verts_a: np.ndarray, verts_b: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How deep each vertex of one body lies inside the other, inside/outside decided by the
    generalised winding number (:class:`~dualhuman_builder.geometry.collision.CollisionTerm` with
    ``sign="winding"``: exact depths, banded query plus sign flood fill).

    ``verts_a``, ``verts_b``: ``(T, V, 3)`` metres (anny's topology). Returns ``depth_a (T, V)``
    (a's vertices inside b; 0 outside), ``depth_b (T, V)`` (b inside a), float64 metres, and
    ``queried (V,)`` bool: the vertices the query covers (the body surface: eyes and mouth
    interior are never counted, see :func:`~dualhuman_builder.body.topology.collision_faces`).

    Why not the pseudonormal sign of the scenes' banded distances: it is exact only on a closed
    surface that does not cross itself, and a posed body does (an arm pressed into its own
    torso, a shoulder folded at full elevation); there it may call an inside point outside or an
    outside point inside, and a penetration reads much deeper than it is
    (docs/decisions/0022-ground-truth-scenes.md). The banded query also never sees a vertex
    deeper than its band.
    """
    term = _winding_term()
    va, vb = np.asarray(verts_a, np.float32), np.asarray(verts_b, np.float32)
    depth_a, depth_b = np.zeros(va.shape[:2]), np.zeros(vb.shape[:2])
    for s in range(0, len(va), WINDING_CHUNK):
        r = term.penetration(va[s:s + WINDING_CHUNK], vb[s:s + WINDING_CHUNK])
        depth_a[s:s + WINDING_CHUNK], depth_b[s:s + WINDING_CHUNK] = r["depth_a"], r["depth_b"]
    queried = np.zeros(va.shape[1], dtype=bool)
    queried[term.obstacle_vertices] = True
    return depth_a, depth_b, queried


def sign_by_winding(distances: tuple[np.ndarray, np.ndarray], verts_a: np.ndarray, verts_b: np.ndarray,
                    frames=None) -> None:  # fmt: skip
    """Give banded signed distances the winding number's inside/outside, in place.

    ``distances``: ``(T, V)`` per actor (metres, negative inside, NaN beyond the band; any float
    dtype), e.g. from :class:`~dualhuman_builder.geometry.distance.PairDistance` (pseudonormal
    sign); ``verts_a``, ``verts_b`` ``(T, V, 3)`` metres; ``frames``: indices to fix (default
    all). On the vertices :func:`winding_depths` covers, a vertex inside the other body gets
    ``-depth`` (also when deeper than the band, where it was NaN) and one outside ``+|d|``;
    magnitudes are unchanged (the closest surface point is the same).
    """
    frames = np.arange(len(verts_a)) if frames is None else np.asarray(frames, dtype=np.int64)
    if not len(frames):
        return
    depth_a, depth_b, queried = winding_depths(np.asarray(verts_a)[frames], np.asarray(verts_b)[frames])
    for d, depth in zip(distances, (depth_a, depth_b)):
        x = d[frames].astype(np.float64)
        inside = (depth > 0) & queried
        outside = ~inside & queried & (x < 0)
        x[inside] = -depth[inside]
        x[outside] = -x[outside]
        d[frames] = x.astype(d.dtype)

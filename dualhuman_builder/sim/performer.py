"""One simulated actor: turns per-frame controls (where the pelvis is, where the feet and palms
go, where the eyes look) into anny pose parameters, with closed-form IK.

Controls are world-frame arrays over ``T`` frames (metres, radians; Y-up, floor at y = 0):

* ``root (T, 3)``: pelvis centre (the root bone head); ``heading (T,)``: yaw about +Y, 0 = facing +Z;
* ``trunk (T, 3)``: the whole trunk's bend as a rotation vector in the body's own axes
  (x = left: positive flexes forward; y = up: positive twists left; z = forward: positive bends
  right), spread evenly over anny's five spine bones;
* ``pelvis (T, 3)`` or None: the pelvis's own tilt, a rotation vector in the same body axes, about
  the root (the legs follow it; the trunk rides on it);
* ``look_at (T, 3)`` or None: a point the head turns towards (at most 60 degrees, half in the neck);
* ``feet["L"|"R"]``: :class:`FootTrack` — ankle (foot bone head) position and foot yaw; the sole
  stays flat;
* ``arms["L"|"R"]``: :class:`ArmTrack` — the palm centre's target, the elbow's pole direction,
  the palm normal and optionally the finger direction; None leaves the arm hanging relaxed.

Every frame is solved independently and exactly, so targets that are continuous in time give
continuous motion, and a foot target held still is a foot that does not slide.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from dualhuman_builder.body.hands import hand_axes, open_hand
from dualhuman_builder.sim.ik import LimbChain, axis_angle, map_frames, normalize, rot_y
from dualhuman_builder.sim.skeleton import Skeleton

SIDES = {"L": 1.0, "R": -1.0}  # the body's left is +X at identity orientation
SPINE = ("spine05", "spine04", "spine03", "spine02", "spine01")


@dataclass
class FootTrack:
    ankle: np.ndarray  # (T, 3)
    heading: np.ndarray  # (T,)


@dataclass
class ArmTrack:
    palm: np.ndarray  # (T, 3) target of the palm centre
    pole: np.ndarray  # (T, 3) direction the elbow points to
    palm_normal: np.ndarray  # (T, 3) direction the palm faces
    fingers: np.ndarray | None = None  # (T, 3) direction the fingers point; default: along the reach
    flat: np.ndarray | None = None  # (T,) in [0, 1]: 0 the relaxed rest hand, 1 fingers and thumb straight in the palm plane
    swivel: np.ndarray | None = None  # (T,) radians: the elbow turned about the shoulder-palm axis


@dataclass
class Controls:
    root: np.ndarray
    heading: np.ndarray
    feet: dict[str, FootTrack]
    trunk: np.ndarray | None = None
    look_at: np.ndarray | None = None
    arms: dict[str, ArmTrack | None] = field(default_factory=lambda: {"L": None, "R": None})
    pelvis: np.ndarray | None = None

    @property
    def frames(self) -> int:
        return len(self.root)

    def take(self, frames) -> "Controls":
        """These controls at the given frame indices (any order, repeats allowed)."""
        idx = np.asarray(frames)
        pick = lambda a: None if a is None else np.asarray(a)[idx]  # noqa: E731
        arms = {s: None if a is None else ArmTrack(pick(a.palm), pick(a.pole), pick(a.palm_normal), pick(a.fingers),
                                                   pick(a.flat), pick(a.swivel))
                for s, a in self.arms.items()}  # fmt: skip
        feet = {s: FootTrack(pick(f.ankle), pick(f.heading)) for s, f in self.feet.items()}
        return Controls(pick(self.root), pick(self.heading), feet, pick(self.trunk), pick(self.look_at), arms,
                        pick(self.pelvis))  # fmt: skip


class Performer:
    """An actor of a given shape: its skeleton, limb chains and hand/foot geometry."""

    def __init__(self, model, shape):
        import torch

        self.model = model
        self.sk = Skeleton.from_model(model, shape)
        with torch.no_grad():
            verts = model.rest(model.shape_tensor(shape)).vertices[0].double().numpy()
        self.rest_vertices = verts
        sk, r = self.sk, self.sk.rest
        self.floor_offset = -verts[:, 1].min()  # root height above the floor at rest
        self.arms = {s: LimbChain(sk, f"upperarm01.{s}", f"lowerarm01.{s}", f"wrist.{s}", twist=f"lowerarm02.{s}")
                     for s in SIDES}  # fmt: skip
        self.legs = {s: LimbChain(sk, f"upperleg01.{s}", f"lowerleg01.{s}", f"foot.{s}") for s in SIDES}
        from dualhuman_builder.body.regions import load_regions

        regions = load_regions(model)
        self.hand = {s: _hand_geometry(sk, verts, regions.vertices_of(("left" if s == "L" else "right") + "_hand"), s)
                     for s in SIDES}  # fmt: skip
        self.flat_hand = {s: open_hand(sk.names, sk.parents, r, verts, model.vertex_bone(), s) for s in SIDES}
        self.ankle_height = {s: r[sk.index(f"foot.{s}"), 1] + self.floor_offset for s in SIDES}
        self.hip_half_width = abs(r[sk.index("upperleg01.L"), 0])
        trunk = ("head", "neck", "chest", "upper_back", "abdomen", "lower_back", "pelvis_front", "buttocks")
        self._trunk_mask = np.isin(regions.vertex_region, [regions.names.index(n) for n in trunk])
        import trimesh

        self._vertex_normals = np.asarray(trimesh.Trimesh(verts, model.faces.cpu().numpy(), process=False).vertex_normals)
        self.stature = verts[:, 1].max() - verts[:, 1].min()

    # ------------------------------------------------------------------ helpers for scene design
    def body_point(self, root: np.ndarray, heading: np.ndarray, offset) -> np.ndarray:
        """World points ``(T, 3)`` at ``offset`` = (left, up, forward) metres from the pelvis."""
        off = np.broadcast_to(np.asarray(offset, dtype=np.float64), np.shape(root))
        return root + np.einsum("tij,tj->ti", rot_y(heading), off)

    def body_dir(self, heading: np.ndarray, direction) -> np.ndarray:
        d = np.broadcast_to(np.asarray(direction, dtype=np.float64), np.shape(heading) + (3,))
        return np.einsum("tij,tj->ti", rot_y(heading), normalize(d))

    def surface_offset(self, face: str, left: float, up: float, radius: float = 0.03) -> np.ndarray:
        """(left, up, forward) offset from the pelvis of the trunk's surface at the rest pose:
        the most forward (``face="front"``) or most backward (``"back"``) vertex of the head,
        neck or torso within ``radius`` of the given left/up offsets (metres)."""
        v = self.rest_vertices
        near = (np.abs(v[:, 0] - left) < radius) & (np.abs(v[:, 1] - up) < radius) & self._trunk_mask
        if not near.any():
            raise ValueError(f"no trunk surface at left={left:.2f} m, up={up:.2f} m")
        z = v[near, 2].max() if face == "front" else v[near, 2].min()
        return np.array([left, up, z])

    def reach_forward(self, side: str, up: float, left: float, frac: float = 0.85) -> float:
        """How far in front of the pelvis (m) a palm at ``up``/``left`` (pelvis-relative, standing)
        is when it sits at ``frac`` of the arm's reach from the shoulder."""
        s = self.sk.rest[self.sk.index(f"upperarm01.{side}")] + [0.0, self.floor_offset - self.standing_height(), 0.0]
        reach = frac * (self.arms[side].reach + np.linalg.norm(self.hand[side].palm_offset))
        rest2 = reach**2 - (up - s[1]) ** 2 - (left - s[0]) ** 2
        if rest2 <= 0:
            raise ValueError(f"a palm at {up:.2f} m up, {left:.2f} m left is out of the arm's reach")
        return float(s[2] + np.sqrt(rest2))

    def attached_point(self, c: Controls, bone: str, rest_point: np.ndarray, rest_direction=None):
        """World positions ``(T, 3)`` of a point fixed to ``bone`` (given at the rest pose with the
        pelvis at the origin) as the body moves under controls ``c`` (trunk and pelvis; arms
        ignored); with ``rest_direction``, also that direction carried along ``(T, 3)``."""
        local, transl = self.solve(Controls(c.root, c.heading, c.feet, c.trunk, pelvis=c.pelvis))
        heads, glob = self.sk.fk(local, transl)
        i = self.sk.index(bone)
        point = heads[:, i] + np.einsum("tij,j->ti", glob[:, i], np.asarray(rest_point) - self.sk.rest[i])
        if rest_direction is None:
            return point
        return point, np.einsum("tij,j->ti", glob[:, i], np.asarray(rest_direction, dtype=np.float64))

    def surface_anchor(self, face: str, a: float, up: float, radius: float = 0.03) -> tuple[np.ndarray, np.ndarray]:
        """A trunk surface point at the rest pose (pelvis at the origin) and its outward normal:
        ``face`` "back" or "front" with ``a`` its left offset, or "left"/"right" with ``a`` its
        forward offset; ``up`` its height above the pelvis (metres)."""
        v = self.rest_vertices
        lateral = face in ("left", "right")
        near = (np.abs(v[:, 2 if lateral else 0] - a) < radius) & (np.abs(v[:, 1] - up) < radius) & self._trunk_mask
        if not near.any():
            raise ValueError(f"no trunk surface on the {face} at {a:.2f} m, up {up:.2f} m")
        key = {"front": v[:, 2], "back": -v[:, 2], "left": v[:, 0], "right": -v[:, 0]}[face]
        j = np.flatnonzero(near)[np.argmax(key[near])]
        return v[j], self._vertex_normals[j]

    def standing_feet(self, root: np.ndarray, heading: np.ndarray, stance: float = 0.0) -> dict[str, FootTrack]:
        """Feet under the hips (plus ``stance`` m wider each), flat, pointing along ``heading``."""
        feet = {}
        for s, sign in SIDES.items():
            r = self.sk.rest[self.sk.index(f"foot.{s}")]
            ankle = self.body_point(root, heading, (r[0] + sign * stance, 0.0, r[2]))
            ankle[:, 1] = self.ankle_height[s]
            feet[s] = FootTrack(ankle, np.array(heading, dtype=np.float64))
        return feet

    def standing_height(self, knee_bend: float = 0.01) -> float:
        """Pelvis height (m) standing with nearly straight legs."""
        return self.floor_offset - knee_bend

    def reachable_root(self, c: Controls, margin: float = 0.985, smooth_s: float = 0.15, fps: float = 30.0) -> np.ndarray:
        """``c.root`` lowered where a leg could not reach its ankle target (hip-to-ankle beyond
        ``margin`` of the leg's reach), then smoothed so the pelvis never drops abruptly."""
        from scipy.ndimage import gaussian_filter1d, maximum_filter1d

        root = np.array(c.root, dtype=np.float64)
        local = self.sk.identity(c.frames)
        local[:, 0] = rot_y(np.asarray(c.heading, dtype=np.float64))
        drop = np.zeros(c.frames)
        for s, leg in self.legs.items():
            hip = self.sk.head(local, root, f"upperleg01.{s}")
            d = c.feet[s].ankle - hip
            horiz2 = d[:, 0] ** 2 + d[:, 2] ** 2
            allowed = np.sqrt(np.maximum((margin * leg.reach) ** 2 - horiz2, 0.0))
            drop = np.maximum(drop, -d[:, 1] - allowed)  # hip must be at most `allowed` above the ankle
        width = max(1, int(round(smooth_s * fps)))
        drop = gaussian_filter1d(maximum_filter1d(drop, 2 * width + 1), width / 2.0)
        root[:, 1] -= np.maximum(drop, 0.0)
        return root

    def shoulder(self, local: np.ndarray, transl: np.ndarray, side: str) -> np.ndarray:
        return self.sk.head(local, transl, f"upperarm01.{side}")

    # ------------------------------------------------------------------ solving
    def solve(self, c: Controls) -> tuple[np.ndarray, np.ndarray]:
        """Pose parameters for the controls: local rotations ``(T, J, 3, 3)`` and root ``(T, 3)``."""
        T, sk = c.frames, self.sk
        local = sk.identity(T)
        transl = np.asarray(c.root, dtype=np.float64)
        local[:, 0] = rot_y(np.asarray(c.heading, dtype=np.float64))
        if c.pelvis is not None:
            tilt = np.asarray(c.pelvis, dtype=np.float64)
            angle = np.linalg.norm(tilt, axis=-1)
            local[:, 0] = local[:, 0] @ axis_angle(np.where(angle[:, None] > 1e-12, tilt, [1.0, 0, 0]), angle)
        if c.trunk is not None:
            bend = np.asarray(c.trunk, dtype=np.float64) / len(SPINE)
            angle = np.linalg.norm(bend, axis=-1)
            step = axis_angle(np.where(angle[:, None] > 1e-12, bend, [1.0, 0, 0]), angle)
            for b in SPINE:
                local[:, sk.index(b)] = step
        for s, leg in self.legs.items():
            f = c.feet[s]
            # knees point forward, between the pelvis's and the foot's headings
            knee_pole = self.body_dir(c.heading, (0.0, 0.0, 1.0)) + self.body_dir(f.heading, (0.0, 0.0, 1.0))
            leg.solve(local, transl, f.ankle, knee_pole, end_rotation=rot_y(f.heading))
        for s in self.arms:
            track = c.arms.get(s) or self.relaxed_arm(local, transl, c.heading, s)
            self._solve_arm(local, transl, c.heading, s, track)
        if c.look_at is not None:
            self._look(local, transl, c.look_at)
        return local, transl

    def relaxed_arm(self, local, transl, heading, side: str) -> ArmTrack:
        """Arms hanging at the sides, palms facing the thighs, elbows slightly back."""
        sign = SIDES[side]
        shoulder = self.shoulder(local, transl, side)
        reach = self.arms[side].reach + np.linalg.norm(self.hand[side].palm_offset)
        palm = shoulder + self.body_dir(heading, (sign * 0.12, -1.0, 0.04)) * reach * 0.93
        return ArmTrack(palm=palm, pole=self.body_dir(heading, (sign * 0.3, 0.0, -1.0)),
                        palm_normal=self.body_dir(heading, (-sign, 0.0, 0.0)),
                        fingers=self.body_dir(heading, (0.0, -1.0, 0.05)))  # fmt: skip

    def _solve_arm(self, local, transl, heading, side: str, track: ArmTrack) -> None:
        if track.flat is not None:
            from dualhuman_builder.sim.ik import _scale_rotation

            for bone, rot in self.flat_hand[side].items():
                local[:, bone] = _scale_rotation(np.broadcast_to(rot, (len(track.flat), 3, 3)), np.asarray(track.flat))
        hand = self.hand[side]
        shoulder = self.shoulder(local, transl, side)
        fingers = track.fingers if track.fingers is not None else track.palm - shoulder
        A_hand = map_frames(hand.fingers0, hand.normal0, fingers, track.palm_normal)
        # twice: the second pass places the palm with the orientation the wrist could reach
        for _ in range(2):
            wrist_target = track.palm - np.einsum("tij,j->ti", A_hand, hand.palm_offset)
            back = self.body_dir(heading, (SIDES[side] * 0.3, -0.2, -1.0))  # elbows back and out
            _, achieved = self.arms[side].solve(local, transl, wrist_target, track.pole, end_rotation=A_hand,
                                                fallback_pole=back, swivel=track.swivel)  # fmt: skip
            A_hand = achieved

    def _look(self, local, transl, target) -> None:
        sk = self.sk
        heads, glob = sk.fk(local, transl)
        i_neck, i_head = sk.index("neck01"), sk.index("head")
        parent = glob[:, int(sk.parents[i_neck])]
        face = parent @ np.array([0.0, 0.0, 1.0])
        want = normalize(target - heads[:, i_head])
        axis = np.cross(face, want)
        angle = np.minimum(np.arccos(np.clip((face * want).sum(-1), -1, 1)), np.radians(60.0))
        half = axis_angle(np.where(np.linalg.norm(axis, axis=-1, keepdims=True) > 1e-9, axis, [1.0, 0, 0]), angle / 2)
        L = np.swapaxes(parent, -1, -2) @ half @ parent
        local[:, i_neck] = L
        local[:, i_head] = L


@dataclass
class _HandGeometry:
    fingers0: np.ndarray  # rest direction wrist -> middle knuckle
    normal0: np.ndarray  # rest palm normal (out of the palm)
    palm_offset: np.ndarray  # rest palm centre - rest wrist head
    palm_vertex: int  # the mesh vertex at the palm centre


def _hand_geometry(sk: Skeleton, verts: np.ndarray, hand_vertices: np.ndarray, side: str) -> _HandGeometry:
    r = sk.rest
    wrist, knuckle = r[sk.index(f"wrist.{side}")], r[sk.index(f"finger3-1.{side}")]
    fingers0, normal0 = hand_axes(sk.names, r, side)
    centre = wrist + 0.55 * (knuckle - wrist)
    v = verts[hand_vertices] - centre
    along = v @ normal0
    off_axis = np.linalg.norm(v - along[:, None] * normal0, axis=1)
    candidates = np.flatnonzero(along > 0)
    best = candidates[np.argmin(off_axis[candidates])]
    return _HandGeometry(fingers0, normal0, verts[hand_vertices[best]] - wrist, int(hand_vertices[best]))

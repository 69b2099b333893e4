"""Each actor's constants for the fit, as torch tensors: :class:`ActorTensors`, and both actors stacked
(:class:`ActorStack`) so the skeleton energy runs as one set of operations.

Conventions: Y-up world, metres; ``S = 23`` driven segments (MVN order), ``T`` timeline frames, ``K``
trackers. The fit's variables are per frame a correction ``delta (S, 3)`` (world-frame rotation vectors
applied to each driven bone's retargeted global rotation), a root offset ``dtransl (3,)`` (m) from the
fused pelvis and the hand openings ``opening (4,)``.
"""

from __future__ import annotations

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.fit.config import FitConfig
from dualhuman_builder.fit.inputs import ActorInput, FitError
from dualhuman_builder.fit.skeleton import BodyRig, linear_pose, rotvec_to_rotmat


def _fill(rot: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Bridge invalid frames of ``rot (T, S, 4)`` (xyzw) by slerp between the nearest valid ones (held
    at the ends)."""
    if valid.all():
        return rot
    if not valid.any():
        raise FitError("no frame of the suit stream is valid")
    t = np.arange(len(rot))
    good = np.flatnonzero(valid)
    out = rot.copy()
    for s in range(rot.shape[1]):
        r = Rotation.from_quat(rot[good, s])
        tt = np.clip(t, good[0], good[-1])
        out[:, s] = Slerp(good, r)(tt).as_quat() if len(good) > 1 else np.repeat(rot[good, s], len(t), 0)
    return out


def _interp_rows(x: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Rows of ``x (T, n)`` bridged linearly over frames that are not ``valid (T,)`` or not finite."""
    from dualhuman_builder.fit.fuse import bridge_rows

    return bridge_rows(np.nan_to_num(x), valid & np.isfinite(x).all(-1))


def stance_mask(ankles: np.ndarray, fps: float, sole_offset: np.ndarray, cfg: FitConfig) -> np.ndarray:
    """``(T, 2)`` bool: foot in stance (ankle slower than ``cfg.stance_speed_m_s``, sole within
    ``cfg.stance_height_m`` of the floor). ``ankles (T, 2, 3)`` m; ``sole_offset (2,)``: ankle height
    above the sole at rest (m)."""
    v = np.zeros(ankles.shape[:2])
    v[1:] = np.linalg.norm(np.diff(ankles, axis=0), axis=-1) * fps
    v[0] = v[1] if len(v) > 1 else 0.0
    low = ankles[..., 1] - sole_offset[None] < cfg.stance_height_m
    return (v < cfg.stance_speed_m_s) & low


#: Weight of the orientation term on a segment no sensor measured (:attr:`~.inputs.ActorInput.segment_weight`
#: 0): small, not 0, so the bone stays determined where nothing else moves it.
UNMEASURED_WEIGHT = 0.01


class ActorTensors:
    """One actor's constants on ``cfg.device``: the rig of its shape, the retargeted bone rotations
    ``target (T, S, 3, 3)``, the fused root ``transl0 (T, 3)``, the trackers, the stance mask ``(T, 2)``
    and what the skeleton terms read, registered with the rig as one linear map (``"skeleton"``)."""

    def __init__(self, model, inp: ActorInput, fps: float, cfg: FitConfig, soles: dict, slots: int):
        """``soles``: the sole vertices (:func:`~dualhuman_builder.fit.skeleton.sole_vertices`);
        ``slots``: tracker slots of the skeleton terms' heads, at least this actor's ``K`` (the rest are
        padding, the root's head, never valid, so both actors' terms stack, :class:`ActorStack`)."""
        dev, dt = torch.device(cfg.device), torch.float32
        self.name = inp.name
        self.rig = BodyRig(model, inp.shape, device=dev)
        self.n_sole = len(soles["L"])
        valid = np.asarray(inp.valid, bool)
        rot = _fill(np.asarray(inp.seg_rot, np.float64), valid)
        frames = torch.as_tensor(Rotation.from_quat(rot.reshape(-1, 4)).as_matrix().reshape(*rot.shape[:2], 3, 3), dtype=dt, device=dev)
        self.target = self.rig.retarget(frames)  # (T, S, 3, 3)
        self.transl0 = torch.as_tensor(_interp_rows(np.asarray(inp.pelvis, np.float64), valid), dtype=dt, device=dev)
        self.valid = torch.as_tensor(valid, device=dev)
        # trust in each segment's measured orientation: an unmeasured one (an upper-body recording's legs)
        # keeps a weak pull to the suit's pose so the smoothness, floor and stance terms decide it
        w = np.ones(len(MVN_SEGMENTS)) if inp.segment_weight is None else np.asarray(inp.segment_weight, np.float64)
        self.seg_w = torch.as_tensor(np.maximum(w, UNMEASURED_WEIGHT), dtype=dt, device=dev)  # (S,)
        self.trk_pos = torch.as_tensor(np.nan_to_num(inp.trk_pos), dtype=dt, device=dev)
        self.trk_valid = torch.as_tensor(np.asarray(inp.trk_valid, bool) & valid[:, None], device=dev)
        self.trk_seg = torch.as_tensor(np.asarray(inp.trk_segment, np.int64), device=dev)
        self.trk_bone = self.rig.segment_bones[self.trk_seg] if len(inp.trk_segment) else self.trk_seg
        self.trk_off = torch.as_tensor(np.asarray(inp.trk_offset, np.float64), dtype=dt, device=dev)
        # what the skeleton terms read, linear in the driven rotations (BodyRig.pose_linear): the 22
        # joints, the trackers' bones (padded to `slots` with the root), the two feet's bones, the sole vertices
        self.joints = self.rig.model.joint22_index.to(dev)
        self.slots = int(slots)
        foot = self.rig.segment_bones[[MVN_SEGMENTS.index("LeftFoot"), MVN_SEGMENTS.index("RightFoot")]]
        pad = torch.zeros(self.slots - len(self.trk_bone), dtype=torch.int64, device=dev)
        self.rig.add_linear("skeleton", torch.cat([self.joints, self.trk_bone, pad, foot]).cpu().numpy(),
                            np.concatenate([soles["L"], soles["R"]]))  # fmt: skip
        with torch.no_grad():
            eye = torch.eye(3, device=dev).expand(1, len(MVN_SEGMENTS), 3, 3)
            heads, sole = self.skeleton(eye, torch.zeros(1, 3, device=dev))
            ankle_h = heads[2][0, :, 1].cpu().numpy()
            sole_h = np.array([sole[0, : self.n_sole, 1].min().item(), sole[0, self.n_sole :, 1].min().item()])
        ankles = _interp_rows(np.asarray(inp.ankles, np.float64).reshape(len(valid), -1), valid).reshape(-1, 2, 3)
        self.stance = torch.as_tensor(stance_mask(ankles, fps, ankle_h - sole_h, cfg), device=dev)

    def rotations(self, delta, sl):
        """Driven-bone rotations ``(n, S, 3, 3)`` of timeline frames ``sl`` with the corrections
        ``delta (n, S, 3)``."""
        return rotvec_to_rotmat(delta) @ self.target[sl]

    def skeleton(self, rot, transl):
        """What the skeleton terms read of driven-bone rotations ``rot (n, S, 3, 3)`` and root
        positions ``transl (n, 3)`` (m): the heads ``((n, 22, 3) joints, (n, slots, 3) the trackers'
        bones, (n, 2, 3) the feet's)`` and the sole vertices ``(n, 2 n_sole, 3)`` (left then right)."""
        heads, soles = self.rig.pose_linear(rot, transl, "skeleton")
        return split_heads(heads, len(self.joints), self.slots), soles

    def pose(self, delta, dtransl, sl, vertices=True, opening=None):
        """``(rot, posed)``: the driven-bone rotations and the rig's pose (bones, and ``vertices``) of
        timeline frames ``sl`` (a slice or an index tensor) with the corrections ``delta (n, S, 3)``,
        ``dtransl (n, 3)`` (m) and the hand openings ``opening (n, 4)`` (None: relaxed hands)."""
        rot = self.rotations(delta, sl)
        return rot, self.rig.pose(rot, self.transl0[sl] + dtransl, vertices, opening)


def split_heads(heads: torch.Tensor, nj: int, K: int) -> tuple:
    """The skeleton terms' heads ``(..., nj + K + 2, 3)`` as (joints, trackers' bones, feet's)."""
    return heads[..., :nj, :], heads[..., nj : nj + K, :], heads[..., nj + K :, :]


class ActorStack:
    """The actors' constants stacked along a first axis ``A`` (actors), the trackers padded to the most
    any actor has (``Kp``, :class:`ActorTensors`' ``slots``; a padded tracker is never valid): one set of
    tensor operations for both actors instead of one per actor (a skeleton evaluation is ~100 small
    operations, whose cost is their count, not their size)."""

    def __init__(self, acts: list[ActorTensors]):
        dev = acts[0].target.device
        K = acts[0].slots
        self.K, self.nj, self.n_sole = K, len(acts[0].joints), acts[0].n_sole
        pad = [K - len(a.trk_seg) for a in acts]
        self.target = torch.stack([a.target for a in acts])  # (A, T, S, 3, 3)
        self.transl0 = torch.stack([a.transl0 for a in acts])  # (A, T, 3)
        self.valid = torch.stack([a.valid for a in acts]).float()  # (A, T)
        self.seg_w = torch.stack([a.seg_w for a in acts])  # (A, S)
        self.stance = torch.stack([a.stance for a in acts])  # (A, T, 2)
        z = torch.zeros
        self.trk_seg = torch.stack([torch.cat([a.trk_seg, z(p, dtype=torch.int64, device=dev)])
                                    for a, p in zip(acts, pad)])  # (A, Kp)  # fmt: skip
        self.trk_off = torch.stack([torch.cat([a.trk_off, z(p, 3, device=dev)]) for a, p in zip(acts, pad)])  # (A, Kp, 3)
        self.trk_frame = torch.stack([a.rig.seg_frame[s] for a, s in zip(acts, self.trk_seg)])  # (A, Kp, 3, 3)
        T = self.target.shape[1]
        self.trk_pos = torch.stack([torch.cat([a.trk_pos, z(T, p, 3, device=dev)], 1) for a, p in zip(acts, pad)])  # (A, T, Kp, 3)
        self.trk_valid = torch.stack([torch.cat([a.trk_valid, z(T, p, dtype=torch.bool, device=dev)], 1)
                                      for a, p in zip(acts, pad)]).float()  # fmt: skip
        # what each rig's "skeleton" reads (BodyRig.pose_linear), with a frame axis to broadcast over
        linear = [a.rig.linear("skeleton") for a in acts]
        self.mat = torch.stack([m for m, _, _ in linear])[:, None]  # (A, 1, 3S, N)
        self.wsum = torch.stack([w for _, w, _ in linear])[:, None]  # (A, 1, N)
        self.n_heads = linear[0][2]

    def rotations(self, delta, sl):
        """Driven-bone rotations ``(A, n, S, 3, 3)`` of timeline frames ``sl`` with the corrections
        ``delta (A, n, S, 3)``."""
        return rotvec_to_rotmat(delta) @ self.target[:, sl]

    def skeleton(self, rot, transl):
        """:meth:`ActorTensors.skeleton` of every actor at once: ``rot (A, n, S, 3, 3)``, ``transl (A, n,
        3)`` -> heads ``((A, n, 22, 3) joints, (A, n, Kp, 3) trackers' bones, (A, n, 2, 3) feet's)`` and
        soles ``(A, n, 2 n_sole, 3)``."""
        out = linear_pose(rot, transl, self.mat, self.wsum)  # (A, n, N, 3)
        return split_heads(out[:, :, : self.n_heads], self.nj, self.K), out[:, :, self.n_heads :]

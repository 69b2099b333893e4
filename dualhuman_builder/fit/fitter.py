"""Fit stage: both actors' anny bodies over a take, jointly, with an SDF collision term.

Per frame the pose starts from a closed-form retarget of the fused segment orientations onto the
anny bones (:meth:`~dualhuman_builder.fit.skeleton.BodyRig.retarget`); then both actors are refined
together over windows of frames (batched, each window warm-started from the retarget and joined to
the previous window's last frames; groups of windows form segments, fitted independently on
several processes and cross-faded, :func:`layout`, :func:`_seam`), by L-BFGS on::

    E = sum_frames [ |delta|^2 / s_o^2                        orientation: change of each driven bone (deg)
                   + sum_trackers |site - p_tracker|^2 / s_t^2  tracker positions (drift-free reference)
                   + sum_joints |accel|^2 / s_a^2            temporal smoothness (22 joints)
                   + sum_soles relu(-y)^2 / s_f^2             no foot below the floor
                   + sum_stance (min_sole y)^2 / s_c^2        a foot in stance stands on it
                   + sum_stance |sole step|^2 / s_s^2         no sliding while a foot is in stance
                   + sum_hands (o / s_h)^2 + |o''|^2 / s_ha^2  hand openings: relaxed unless pushed ]
      + w_c * collision(verts_a, verts_b)                     SDF term, frames where the bodies are close

``delta (S, 3)``: a world-frame rotation vector applied to each driven bone's retargeted global
rotation (so the orientation data term and the pose regulariser toward the retarget are the same
quadratic); ``transl`` starts at the fused pelvis position. ``o (4,)`` per frame: the openings of
each hand's thumb and fingers (:mod:`dualhuman_builder.body.hands`; 0 anny's relaxed hand, 1 flat,
kept within [-0.5, 1]). The suit measures no fingers, so only the collision term moves them: a palm
resting on the partner opens flat instead of leaving the relaxed thumb and fingertips inside them
(the thumb stands ~3 cm out of the palm plane; the wrist's orientation data hold the palm). Each
window's collision passes start with one over the openings alone, then the full rounds. That pass
reads only what the openings change: the located contacts touching a finger
(:meth:`~dualhuman_builder.geometry.collision.CollisionTerm.moving_only`) and the openings' own terms
(:func:`_opening_energy`), the bones held as constants (no gradient into them). Each pass weights
the term ``collision_weight_step`` (4) times the one before; a frame that the full rounds start with
deeper than ``collision_deep_m`` (1 cm) is weighted one step ahead of the others from round 1 on:
past the robust loss's 1 cm scale a vertex's push stops growing with its depth, and such a frame
barely moved in round 1. Each full round moves only the frames the pass before it left over a
tolerance and the two on either side of them (``collision_hold_settled``); the settled ones are held
where they are, and the check after the round measures only the frames it moved.

The skeleton terms read ~30 bone heads and ~80 sole vertices per actor, linear in the 23 driven
rotations (:meth:`~dualhuman_builder.fit.skeleton.BodyRig.pose_linear`: one matrix product; a
48-frame window's energy and gradient, both actors, in ~7 ms instead of ~21 through the whole
rig; both actors as one stack of tensors, :class:`_Stack`, 5.5-6.5 -> 4.1-4.4 ms on 2026-11-26, a script
outside the repo);
the full meshes are skinned only for frames whose bodies penetrate after the skeleton pass
(measured with :class:`~dualhuman_builder.geometry.collision.CollisionTerm`), and only those frames get
the collision pass (their full meshes skinned without gradient, to find the
contacts; the few thousand (frame, vertex) pairs the loss reads are skinned again with it,
:meth:`~dualhuman_builder.fit.skeleton.BodyRig.skin_at`). Frames far apart pay nothing. The collision term is
called with the frames' timeline indices as keys, so each evaluation reuses the signs of the last
one where the bodies moved too little to change them (the same answer wherever the pseudonormal sign
is well defined; see :mod:`~dualhuman_builder.geometry.collision`). By default
(``FitConfig.collision_hold_contacts``) a pass does not locate the contacts at every evaluation: the
check after the previous pass located them (:meth:`~dualhuman_builder.geometry.collision.CollisionTerm.linearise`,
every vertex inside the other body or outside within ``collision_margin_m``), and the pass holds
them, each evaluation re-reading only their positions (point-to-plane, exact in value and gradient
where located; no full-mesh skinning or query per evaluation). Held planes stall where the answer
lies through a thin part of the partner -- a hand 2 cm into the partner's forearm, closer to its far
side than the data allow it to go back: the exact term pushes such a vertex on through and out once
it passes the middle (its closest face changes sides), a held plane keeps pushing it back the way it
came -- and where the closest faces change as the bodies move (interlocked fingers). A full round that
leaves the window's deepest frame deeper than 75 % of where it started (and over the tolerance)
stalled: from the next round on, the frames it left that deep have their contacts located at every
evaluation (exact), the others stay held (``collision_held_stalled``, ``collision_exact_frames`` in
the summary). A window the rounds leave unsettled all the same is fitted again from its skeleton
pass with those frames and every frame they left over the tolerance located at every evaluation,
the rest held (``collision_exact_windows``), and keeps the less deep of the two answers. So is a
window the held rounds settle only after a stall but with its skeleton energy (every term but the
collision term) more than ``collision_energy_ratio`` (2) times the skeleton pass's: held planes can
settle a window by bending the bodies out of shape; of the two settled answers the lower energy is
kept (``collision_energy_refits``). On the
fit benchmark's hug one frame in each of two windows went exact and both windows settled: the fit
took 19 s instead of 40 with those windows refitted whole from their skeleton pass, every contact
exact (the rule before 2026-11-24; traced with a script outside the repo); the accuracy
benchmark's dance turns still refit windows (two and one in its last run).
A collision pass whose line search steps to non-finite corrections is undone and listed in the
summary (``collision_diverged``); so is one that leaves the window's deepest frame deeper than the
best pass before it (``collision_worsened``):
the next round starts again from the best answer, so the rounds never leave a window deeper than
the skeleton pass did. Frames that a full round (from the second on) leaves deeper than the
tolerance and moves by less than 20 % are stuck — on the simulated dance turns, joined hands
interlocked (one's finger in the other's palm, the other's thumb in the first hand), so the term's
two pushes oppose each other however it is weighted: up to twice per window, each run of too-deep
frames holding a stuck one starts the next round from the straight line between the frames just
around it (``collision_restart``; dance turn 1 of the accuracy benchmark: 9.0 -> 1.9 mm with one
restart; after the heading fix of 2026-11-24 in sync its recording left 8.8 mm at frame 82 after
one and 1.2 mm after a second).
"""

# ruff: noqa: B023 -- the L-BFGS closures run inside the loop iteration that defines them

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.errors import DualhumanError
from dualhuman_builder.fit.skeleton import linear_pose, rotvec_to_rotmat


class FitError(DualhumanError):
    """The fit cannot run on this input."""


_MAX_RESTARTS = 2  # restarts of stuck frames per window (see the module docstring)
#: the frames on either side of one whose smoothness terms read it too (the second difference at t - 1, t
#: and t + 1 reads t - 2 .. t + 2): a full round moves these with the frames still over a tolerance
_SMOOTH_REACH = 2


class _Diverged(Exception):
    """An L-BFGS line search stepped to non-finite parameters."""


def _finite(tensors) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in tensors)


def _settled(depth: np.ndarray, share: np.ndarray, cfg: FitConfig) -> bool:
    """Whether frames with per-frame deepest vertices ``depth`` (m) and penetrating shares ``share``
    are all within ``cfg.collision_tolerance_m`` and ``cfg.collision_share_tolerance``."""
    return bool(np.max(depth) <= cfg.collision_tolerance_m and np.max(share) <= cfg.collision_share_tolerance)


def _restore(params, saved) -> None:
    """Copy ``saved`` tensors back into the optimised ``params`` (in place)."""
    with torch.no_grad():
        for p, k in zip(params, saved):
            p.copy_(k)


@dataclass(frozen=True)
class FitConfig:
    """Weights are standard deviations (the terms are squared residuals over them)."""

    window: int = 48
    overlap: int = 4
    #: windows per segment (:func:`layout`): segments are fitted independently (in parallel when there
    #: are workers) and cross-faded over the ``2 overlap`` frames they share; 0: the whole take is one
    segment_windows: int = 2
    iterations: int = 30
    collision: bool = True
    collision_iterations: int = 12
    #: while a window still has a frame deeper than ``collision_tolerance_m`` after a collision pass, it
    #: gets another, up to this many full rounds. Each pass is weighted x4 over the one before it, the
    #: hands' pass included: ``collision_weight`` for the hands, x4 for round 1, x16 for round 2 ... (until
    #: 2026-11-24 round 1 repeated the hands' weight, and in a per-pass trace of the fit benchmark's hug
    #: (a script outside the repo) mostly did nothing where the hands' pass had not: the accuracy
    #: benchmark's twelve fits 85.4 -> 63.0 s with the span below, figures in the README)
    collision_rounds: int = 6
    #: each collision pass's weight over the one before it. 8 instead of 4 on the fit benchmark's 0.5-minute
    #: hug (one process, 2026-11-26, a script outside the repo): 1.07x the speed, MPJPE 2.82 -> 3.39 mm and
    #: the joint error's second difference away from the seams 6.1 -> 14.3 mm/frame^2 (bench_fit's jitter),
    #: so 4 stays
    collision_weight_step: float = 4.0
    #: a frame that the full rounds start with deeper than this (m) has its collision term one weight
    #: step ahead of the others from round 1 on (x16 the hands' weight where they get x4; 0: off). Past
    #: the pseudo-Huber's scale (``CollisionTerm`` ``robust_sigma_m``, 1 cm) a vertex's push no longer
    #: grows with its depth, so a deep overlap (a hug's arm 3 cm into the partner after the skeleton
    #: pass) barely moved in round 1 and every window in contact spent a round on it: on the fit
    #: benchmark's 0.5-minute hug (one process, 2026-11-27, a script outside the repo) 78 -> 56 full
    #: rounds, MPJPE 2.89 -> 3.08 mm; 1 cm and 2 cm there gave the same rounds, 5 mm 58; two steps
    #: ahead, or another step for each round a frame stays that deep, were slower. Figures in the README
    collision_deep_m: float = 0.01
    collision_tolerance_m: float = 0.002
    #: ... or a frame has more than this share of both bodies' vertices inside the other (any depth; 0.05 %:
    #: half the issue's goal, so a palm resting a millimetre deep on the partner goes round again too)
    collision_share_tolerance: float = 0.0005
    #: up to twice per window (``_MAX_RESTARTS``), frames that a full round left deeper than the
    #: tolerance and barely moved (less than 20 %) start the next round from their neighbours' answer
    collision_restart: bool = True
    #: where the held rounds settle a window only after some of its frames stalled (located exactly from
    #: then on), but leave its skeleton energy (every term but the collision term) more than this many
    #: times what the skeleton pass left, the window is fitted again the exact way too, and of the two
    #: settled answers the lower energy is kept (0: off). Held planes that stalled can settle a window
    #: by bending the bodies out of shape: on the accuracy benchmark's recordings dance turn 1's first
    #: window settled held at 23.3x, exact at 2.8x (the take's MPJPE 10.17 -> 8.86 mm with the refits);
    #: dance turn 2's one refit kept its held answer (2.6x against 3.2x). The fit benchmark's hug settles
    #: its windows at 1.0-1.3x and never refits (2026-11-27, scripts outside the repo; README)
    collision_energy_ratio: float = 2.0
    #: a window's collision passes move the frames within this many seconds of a frame the skeleton pass
    #: left in contact, and those between; the rest of the window keeps its skeleton pass (0: the whole
    #: window moves). The smoothness terms couple each frame to its two neighbours on either side, so a
    #: push fades out over a few frames; 0.3 s was not swept (only it and 0 were measured)
    collision_span_s: float = 0.3
    #: each collision pass locates the contacts where it starts and holds them through its L-BFGS
    #: evaluations (:class:`~dualhuman_builder.geometry.collision.Linearised`: an evaluation re-reads the
    #: contacts' positions only), except in frames where a held round stalled; a window the rounds do
    #: not settle is fitted again from its skeleton pass with those frames and the ones left too deep
    #: located at every evaluation (see the module docstring). False: every contact located at every
    #: evaluation (the fit benchmark's hug: 2.7-3.1x slower on 2026-11-24; 1.25x over the accuracy
    #: benchmark's twelve takes on 2026-11-23, before stalls went exact frame by frame: ``--compare-exact``)
    collision_hold_contacts: bool = True
    #: each full round moves only the frames the pass before it left over a tolerance and the two on either
    #: side of them (the frames their smoothness terms read), and only frames the round before it moved;
    #: the rest, settled, are held where they are: their collision term is a constant, left out, and the
    #: check after the round measures only the frames it moved. On the fit benchmark's 0.5-minute hug a
    #: round after the first typically left 0-6 of a window's 48 frames over a tolerance; the checks
    #: measured 3,098 frames instead of 4,405 for 59 full rounds instead of 57, MPJPE 3.05 -> 2.89 mm, the
    #: jitter away from seams 5.9 -> 6.2 mm/frame^2 (with a frame on either side instead of two: 2,937 and
    #: 6.25; with 0.3 s, ``collision_span_s``: 3,925 and 5.8; 2026-11-27, a script outside the repo).
    #: False: every round moves the whole span
    collision_hold_settled: bool = True
    #: vertices outside the other body within this distance (m) are held with the contacts, so the
    #: held term sees them cross in
    collision_margin_m: float = 0.005
    sigma_orientation_deg: float = 2.0
    sigma_tracker_m: float = 0.004
    #: joint acceleration, m/s^2 (scaled to a per-frame second difference by fps)
    sigma_accel_m_s2: float = 4.0
    sigma_floor_m: float = 0.002
    sigma_slide_m: float = 0.002
    #: a foot in stance stands on the floor: its lowest sole vertex at height 0 (m); 0 turns
    #: the term off (then nothing but the trackers holds a standing body down)
    sigma_contact_m: float = 0.002
    #: the collision loss is a mean over both meshes' vertices (~27,000): this makes a vertex 2 mm deep
    #: cost about as much as a tracker 4 mm off
    collision_weight: float = 3e5
    #: a foot is in stance when its ankle moves slower than this (m/s) ...
    stance_speed_m_s: float = 0.15
    #: ... and its sole is within this height of the floor (m)
    stance_height_m: float = 0.03
    #: let the collision passes open the hands (thumb and fingers, :mod:`dualhuman_builder.body.hands`)
    hand_opening: bool = True
    #: prior on each opening (0 relaxed, 1 flat): opening a hand flat costs as much as a tracker 8 mm off
    sigma_hand_opening: float = 0.5
    #: second difference of the openings, per s^2 (scaled by fps like the joint acceleration)
    sigma_hand_opening_accel_s2: float = 40.0
    device: str = "cpu"
    #: torch's intra-op CPU threads during the fit (the caller's setting is restored after); 0: leave
    #: it. With 1 a fit of the same inputs repeats exactly. With 2 it did not: two fits of the fit
    #: benchmark's hug in one process left 1.94 and 1.38 mm, and a dance turn fitted beside two busy
    #: processes moved its bodies by up to 0.24 (pose, radians) against one fitted alone. Which of
    #: torch's multi-threaded CPU kernels rounds differently was not found (MKL_DYNAMIC and
    #: OMP_DYNAMIC set to FALSE did not help; the collision term's own threads count as load). Two
    #: threads were ~10 % faster on that hug (36-39 s against 41 s; these figures from scripts
    #: outside the repo) and ~20 % over the accuracy benchmark's twelve takes (87 s against 106,
    #: partly different L-BFGS paths; ``bench_fit.py --threads 2`` compares). The collision term's
    #: warp queries keep their own threads either way
    torch_threads: int = 1


#: the range the hand openings are held in (soft walls): a little more curled than relaxed, to flat
OPENING_RANGE = (-0.5, 1.0)


@dataclass
class ActorInput:
    """What the fitter needs of one actor (``T`` frames on the timeline)."""

    name: str
    shape: dict
    seg_rot: np.ndarray  # (T, 23, 4) xyzw fused segment orientations, tracker world
    pelvis: np.ndarray  # (T, 3) fused pelvis origin
    valid: np.ndarray  # (T,) frames with suit data
    trk_pos: np.ndarray  # (T, K, 3)
    trk_valid: np.ndarray  # (T, K)
    trk_segment: np.ndarray  # (K,)
    trk_offset: np.ndarray  # (K, 3)
    ankles: np.ndarray  # (T, 2, 3) fused LeftFoot, RightFoot origins (stance detection)


@dataclass
class FitResult:
    """``sequence``: the fitted InteractionSequence; ``frames``: per-frame series (T,) for the
    report; ``summary``: headline numbers; ``valid (T,)``: frames with suit data for both."""

    sequence: object
    frames: dict = field(default_factory=dict)
    summary: dict = field(default_factory=dict)
    valid: np.ndarray | None = None


def _fill(rot: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Bridge invalid frames of ``rot (T, S, 4)`` by slerp between the nearest valid ones (held at
    the ends)."""
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
    from dualhuman_builder.fit.fuse import bridge_rows

    return bridge_rows(np.nan_to_num(x), valid & np.isfinite(x).all(-1))


def stance_mask(ankles: np.ndarray, fps: float, sole_offset: np.ndarray, cfg: FitConfig) -> np.ndarray:
    """``(T, 2)`` bool: foot in stance (slow ankle, sole near the floor). ``sole_offset (2,)``: ankle
    height above the sole at rest."""
    v = np.zeros(ankles.shape[:2])
    v[1:] = np.linalg.norm(np.diff(ankles, axis=0), axis=-1) * fps
    v[0] = v[1] if len(v) > 1 else 0.0
    low = ankles[..., 1] - sole_offset[None] < cfg.stance_height_m
    return (v < cfg.stance_speed_m_s) & low


class _Actor:
    """Tensors of one actor for the fitter."""

    def __init__(self, model, inp: ActorInput, fps: float, cfg: FitConfig, soles: dict, slots: int):
        """``slots``: tracker slots of the skeleton terms' heads, at least this actor's ``K`` (the rest
        are padding, the root's head, never valid: both actors' terms then stack, :class:`_Stack`)."""
        from dualhuman_builder.fit.skeleton import BodyRig

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
        """Driven-bone rotations ``(n, 23, 3, 3)`` of timeline frames ``sl`` with the corrections
        ``delta (n, 23, 3)`` (world-frame rotation vectors on the retarget)."""
        return rotvec_to_rotmat(delta) @ self.target[sl]

    def skeleton(self, rot, transl):
        """What the skeleton terms read of driven-bone rotations ``rot (n, 23, 3, 3)`` and root
        positions ``transl (n, 3)`` (metres): the heads ``((n, 22, 3) joints, (n, slots, 3) the trackers'
        bones, (n, 2, 3) the feet's)`` and the sole vertices ``(n, 2 n_sole, 3)`` (left then right)."""
        heads, soles = self.rig.pose_linear(rot, transl, "skeleton")
        return _split_heads(heads, len(self.joints), self.slots), soles

    def pose(self, delta, dtransl, sl, vertices=True, opening=None):
        """Bones (and ``vertices``) of timeline frames ``sl`` (a slice or an index tensor) with the
        corrections ``delta (n, 23, 3)`` rotation vectors and ``dtransl (n, 3)`` metres, and the
        hand openings ``opening (n, 4)`` (None: relaxed hands)."""
        rot = self.rotations(delta, sl)
        return rot, self.rig.pose(rot, self.transl0[sl] + dtransl, vertices, opening)


def _split_heads(heads: torch.Tensor, nj: int, K: int) -> tuple:
    """The skeleton terms' heads ``(..., nj + K + 2, 3)`` as (joints, trackers' bones, feet's)."""
    return heads[..., :nj, :], heads[..., nj : nj + K, :], heads[..., nj + K :, :]


class _Stack:
    """The actors' constants for :func:`_energy`, stacked along a first axis ``A`` (actors), the
    trackers padded to the most any actor has (``Kp``, :class:`_Actor`'s ``slots``; a padded tracker
    is never valid): one set of tensor operations for both actors instead of one per actor (a skeleton
    evaluation is ~100 small operations, whose cost is their count, not their size)."""

    def __init__(self, acts: list[_Actor]):
        dev = acts[0].target.device
        K = acts[0].slots
        self.K, self.nj, self.n_sole = K, len(acts[0].joints), acts[0].n_sole
        pad = [K - len(a.trk_seg) for a in acts]
        self.target = torch.stack([a.target for a in acts])  # (A, T, S, 3, 3)
        self.transl0 = torch.stack([a.transl0 for a in acts])  # (A, T, 3)
        self.valid = torch.stack([a.valid for a in acts]).float()  # (A, T)
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
        """Driven-bone rotations ``(A, n, 23, 3, 3)`` of timeline frames ``sl`` with the corrections
        ``delta (A, n, 23, 3)``."""
        return rotvec_to_rotmat(delta) @ self.target[:, sl]

    def skeleton(self, rot, transl):
        """:meth:`_Actor.skeleton` of every actor at once: ``rot (A, n, 23, 3, 3)``, ``transl (A, n, 3)`` ->
        heads ``((A, n, 22, 3) joints, (A, n, Kp, 3) trackers' bones, (A, n, 2, 3) feet's)`` and soles
        ``(A, n, 2 n_sole, 3)``."""
        out = linear_pose(rot, transl, self.mat, self.wsum)  # (A, n, N, 3)
        return _split_heads(out[:, :, : self.n_heads], self.nj, self.K), out[:, :, self.n_heads :]


def _energy(st: _Stack, delta, dtransl, opening, sl: slice, ctx, cfg: FitConfig, fps: float, after=None):
    """Skeleton energy of all actors on frames ``sl``, summed: ``delta (A, n, 23, 3)``, ``dtransl (A, n,
    3)``, ``opening (A, n, 4)``; ``ctx``: (joints, soles, openings) of up to two frames before ``sl``
    (fixed, from the previous window; each with the actors' axis first) or None; ``after``: the same
    of up to two frames after it (a seam's window, :func:`_seam`) or None. Returns (energy, rot): ``rot
    (A, n, 23, 3, 3)`` the driven bones' rotations (for the collision passes' full poses)."""
    rot = st.rotations(delta, sl)
    (joints, trk_heads, _), soles = st.skeleton(rot, st.transl0[:, sl] + dtransl)
    s_o = np.radians(cfg.sigma_orientation_deg)
    e = (delta.pow(2).sum((-1, -2)) * st.valid[:, sl]).sum() / s_o**2
    if st.K:
        A, n = rot.shape[:2]
        idx = st.trk_seg[:, None, :, None].expand(A, n, st.K, 9)
        seg_frame = torch.gather(rot.reshape(A, n, -1, 9), 2, idx).reshape(A, n, st.K, 3, 3) @ st.trk_frame[:, None]
        site = trk_heads + (seg_frame @ st.trk_off[:, None, :, :, None])[..., 0]
        r = (site - st.trk_pos[:, sl]).pow(2).sum(-1) * st.trk_valid[:, sl]
        e = e + r.sum() / cfg.sigma_tracker_m**2
    soles_all, stance = soles, st.stance[:, sl]
    if ctx is not None:
        joints = torch.cat([ctx[0], joints], 1)
        soles_all = torch.cat([ctx[1], soles_all], 1)
        stance = torch.cat([st.stance[:, sl.start - ctx[0].shape[1] : sl.start], stance], 1)
    if after is not None:
        joints = torch.cat([joints, after[0]], 1)
        soles_all = torch.cat([soles_all, after[1]], 1)
        stance = torch.cat([stance, st.stance[:, sl.stop : sl.stop + after[0].shape[1]]], 1)
    if joints.shape[1] >= 3:
        acc = joints[:, 2:] - 2 * joints[:, 1:-1] + joints[:, :-2]
        s_a = cfg.sigma_accel_m_s2 / fps**2
        e = e + acc.pow(2).sum() / s_a**2
    e = e + torch.relu(-soles[..., 1]).pow(2).sum() / cfg.sigma_floor_m**2
    n_s = st.n_sole
    if cfg.sigma_contact_m > 0:
        y = torch.stack([soles[..., :n_s, 1], soles[..., n_s:, 1]], 2)  # (A, n, 2, n_sole)
        low = y.amin(-1)  # (A, n, 2); a soft minimum would sit below the lowest of a flat sole's many low points
        e = e + (low.pow(2) * st.stance[:, sl].float()).sum() / cfg.sigma_contact_m**2
    if soles_all.shape[1] >= 2:
        feet = torch.stack([soles_all[:, :, :n_s].mean(2), soles_all[:, :, n_s:].mean(2)], 2)  # (A, n', 2, 3)
        step = (feet[:, 1:] - feet[:, :-1])[..., 0::2].pow(2).sum(-1)  # x and z (0::2: a view, not a gather)
        both = (stance[:, 1:] & stance[:, :-1]).float()
        e = e + (step * both).sum() / cfg.sigma_slide_m**2
    return _opening_energy(opening, ctx, after, cfg, fps, e), rot


def _opening_energy(opening, ctx, after, cfg: FitConfig, fps: float, base=0.0):
    """The hand openings' terms of :func:`_energy`, added to ``base`` (:func:`_energy` passes its bones'
    terms, so the sum keeps its order): the prior toward relaxed hands, the walls of
    :data:`OPENING_RANGE` and the openings' second difference over ``ctx``'s, ``opening (A, n, 4)``'s
    and ``after``'s frames (``ctx``, ``after`` as for :func:`_energy`; only their openings are read).
    The hands' collision pass moves nothing else, so this is all of the skeleton energy that changes
    there."""
    o = torch.cat([x for x in (None if ctx is None else ctx[2], opening, None if after is None else after[2]) if x is not None], 1)
    lo, hi = OPENING_RANGE
    e = base + opening.pow(2).sum() / cfg.sigma_hand_opening**2
    e = e + (torch.relu(opening - hi).pow(2) + torch.relu(lo - opening).pow(2)).sum() / 0.01**2
    if o.shape[1] >= 3:
        s_h = cfg.sigma_hand_opening_accel_s2 / fps**2
        e = e + (o[:, 2:] - 2 * o[:, 1:-1] + o[:, :-2]).pow(2).sum() / s_h**2
    return e


def fit_actors(model, inputs: list[ActorInput], fps: float, cfg: FitConfig = FitConfig(),
               progress: Callable[[str], None] | None = None, workers: int | None = None) -> FitResult:  # fmt: skip
    """Fit one or two actors over the whole timeline (see the module docstring), with torch's CPU
    threads set to ``cfg.torch_threads`` meanwhile.

    The take's segments (:func:`layout`) are fitted on ``workers`` processes, this one included
    (None: :func:`fit_workers`; 1: all in this process); the others are started as ``python -m
    dualhuman_builder.fit.workers``. The answer does not depend on it. ``progress`` gets one line
    per window and collision pass (from any worker, one line at a time)."""
    threads = torch.get_num_threads()
    if cfg.torch_threads > 0:
        torch.set_num_threads(int(cfg.torch_threads))
    try:
        return _fit_actors(model, inputs, fps, cfg, progress, workers)
    finally:
        torch.set_num_threads(threads)


@dataclass
class _Part:
    """One segment's answer, for timeline frames ``start .. start + n - 1``: per actor the corrections
    ``delta (n, 23, 3)`` (rotation vectors), ``dtransl (n, 3)`` (m) and the hand openings ``opening
    (n, 4)``; the depth ``pen_before (n,)`` (m) and penetrating share ``share_before (n,)`` after the
    skeleton pass, ``pen_after``/``share_after`` the same at the answer (None without the collision
    term); and the collision passes' counts and lists (see the summary in :func:`fit_actors`)."""

    start: int
    delta: list
    dtransl: list
    opening: list
    pen_before: np.ndarray
    share_before: np.ndarray
    pen_after: np.ndarray | None = None
    share_after: np.ndarray | None = None
    collided: int = 0
    rounds: int = 0
    diverged: list = field(default_factory=list)  # collision passes that stepped to non-finite values (undone)
    worsened: list = field(default_factory=list)  # collision passes that left the deepest frame deeper than the best (undone)
    exact_frames: list = field(default_factory=list)  # timeline frames located at every evaluation after a stall
    exact_windows: list = field(default_factory=list)  # windows the held rounds did not settle, fitted again exactly
    stalled: list = field(default_factory=list)  # held rounds that stalled
    energy_refits: list = field(default_factory=list)  # windows fitted again exactly for their skeleton energy


def layout(T: int, cfg: FitConfig) -> list[list[tuple[int, int, int]]]:
    """The windows of a ``T``-frame take, ``(index, first frame, end frame)``, grouped into segments.

    Windows of ``cfg.window`` frames start every ``window - overlap`` frames (none that only repeats
    the previous one's last frames). Each group of ``cfg.segment_windows`` consecutive windows is a
    segment (0: the whole take is one): within it each window starts from the previous one's answer
    in their shared frames and its smoothness terms read the previous one's last two frames; a
    segment's first window starts from the retarget alone, and ``overlap`` frames earlier than the
    window layout puts it, so consecutive segments share ``2 overlap`` frames, which
    :func:`_join` cross-fades. Segments are independent, so they can be fitted in any order and
    process, with the same answer."""
    W, O = max(int(cfg.window), 4), max(int(cfg.overlap), 0)
    starts = [s for s in range(0, T, max(W - O, 1)) if s == 0 or s + O < T]
    wins = [(i, s, min(s + W, T)) for i, s in enumerate(starts)]
    m = int(cfg.segment_windows)
    if m <= 0:
        return [wins]
    segments = [wins[i : i + m] for i in range(0, len(wins), m)]
    for seg in segments[1:]:
        i, s0, s1 = seg[0]
        seg[0] = (i, max(s0 - O, 0), s1)
    return segments


def _join(parts: list[_Part], T: int) -> dict:
    """The segments' answers on the whole timeline: ``delta``/``dtransl``/``opening`` lists (per actor)
    of ``(T, ...)`` float32 arrays, ``pen_before``/``share_before`` ``(T,)``. In frames two consecutive
    segments share, the later one's weight rises linearly from ``1 / (n + 1)`` to ``n / (n + 1)`` over
    the ``n`` shared frames (rotation vectors, translations and openings alike: the corrections are
    small, so blending rotation vectors is blending rotations); the depths (``pen_before``,
    ``share_before``, ``pen_after``, ``share_after`` ``(T,)``) are the later segment's (in the
    shared frames :func:`_seam` measures the blend's)."""
    first = parts[0]
    out = {key: [np.zeros((T,) + x.shape[1:], np.float32) for x in getattr(first, key)] for key in ("delta", "dtransl", "opening")}
    for key in ("pen_before", "share_before", "pen_after", "share_after"):
        out[key] = np.zeros(T)
    end = 0  # frames before this are written
    for p in parts:
        a, n = p.start, len(p.pen_before)
        shared = max(0, min(end, a + n) - a)
        w = (np.arange(1, shared + 1) / (shared + 1)).astype(np.float32)
        for key in ("delta", "dtransl", "opening"):
            for dst, src in zip(out[key], getattr(p, key)):
                src = np.asarray(src, np.float32)
                ws = w.reshape(-1, *([1] * (src.ndim - 1)))
                dst[a : a + shared] = (1 - ws) * dst[a : a + shared] + ws * src[:shared]
                dst[a + shared : a + n] = src[shared:]
        for key in ("pen_before", "share_before", "pen_after", "share_after"):
            if getattr(p, key) is not None:
                out[key][a : a + n] = getattr(p, key)
        end = max(end, a + n)
    return out


def fit_workers(segments: int, cfg: FitConfig, cpus: int | None = None, available_bytes: int | None = None) -> int:
    """Processes a fit of ``segments`` segments runs on when the caller does not say (this one
    included): one per CPU, one per segment at most, and no more than leave :data:`WORKER_BYTES`
    of available memory to each; 1 on a GPU (``cfg.device`` other than ``cpu``: one device, and the
    fit's work already runs in parallel there)."""
    if torch.device(cfg.device).type != "cpu" or segments <= 1:
        return 1
    if cpus is None:
        cpus = _cpus()
    if available_bytes is None:
        available_bytes = _available_memory()
    by_memory = max(1, int(available_bytes // WORKER_BYTES)) if available_bytes else cpus
    return max(1, min(cpus, segments, by_memory))


def _cpus() -> int:
    """The CPUs this process may run on."""
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def collision_threads(processes: int, cpus: int | None = None) -> int:
    """The collision term's query threads in each of a fit's ``processes`` (this one included): the CPUs
    shared out among them, at least 1 and at most 8. More threads than CPUs only wait on each other: on
    the fit benchmark's 1-minute hug on 2 processes and 2 CPUs, one thread each instead of two ran at
    28.4, 36.1 and 33.6 pairs/s against 28.0, 31.7 and 29.2 in alternating pairs (2026-11-27, a script
    outside the repo)."""
    return max(1, min(8, (_cpus() if cpus is None else int(cpus)) // max(1, int(processes))))


#: what one more fitting process may need (its peak resident memory on the 1-minute benchmark hug,
#: ``benchmarks/bench_fit.py``, rounded up)
WORKER_BYTES = 2 << 30


def _available_memory() -> int | None:
    """MemAvailable from /proc/meminfo in bytes (None where there is none)."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return None


def _workers_build_it(model) -> bool:
    """Whether worker processes build the same body model (``get_body_model(cfg.device)``: anny, float32)."""
    from dualhuman_builder.body.model import BodyModel

    return isinstance(model, BodyModel) and model.dtype == torch.float32


@dataclass
class _Seam:
    """Where two consecutive segments meet: their shared timeline frames ``b0 .. e - 1``, the depth
    (m) and penetrating share ``(e - b0,)`` their cross-fade leaves there, and the window fitted
    again over them (a :class:`_Part`), or None where the cross-fade was clean."""

    b0: int
    e: int
    depth: np.ndarray
    share: np.ndarray
    fixed: _Part | None = None


def _seam(fitter: _Fitter, prev: _Part, part: _Part, say: Callable[[str], None]) -> _Seam | None:
    """Measure, and fit again where needed, the seam between consecutive segments ``prev`` and ``part``
    (None: they share no frames, or there is no collision term).

    Two segments can leave the bodies apart in their shared frames in different ways (a hand open
    on one side of the partner's arm in one, curled in the other), and the blend between two such
    answers can pass through the partner (the fit benchmark's 1-minute hug: 9.8 mm in one of 20
    seams, from 0.4 and 1.2 mm; traced with a script outside the repo). A seam whose shared frames the blend leaves deeper than
    ``collision_tolerance_m``, or with a larger penetrating share than ``collision_share_tolerance``,
    is fitted again as one window over those frames and ``overlap`` more on each side, starting
    from the blend, with the two frames on either side fixed as context (so it joins both
    segments smoothly). Needs only the two segments, so it runs as soon as both are done."""
    cfg = fitter.cfg
    b0, e = part.start, prev.start + len(prev.pen_before)
    if fitter.collide is None or e <= b0:
        return None
    a = prev.start
    local = _join([dataclasses.replace(prev, start=0), dataclasses.replace(part, start=part.start - a)],
                  part.start + len(part.pen_before) - a)  # fmt: skip
    fitter.collide.clear_memo()  # measured the same whichever segments this process fitted before
    depth, share = fitter.depths(b0, e, local["delta"], local["dtransl"], local["opening"], origin=a)
    seam = _Seam(b0, e, depth, share)
    if not _settled(depth, share, cfg):
        O = max(int(cfg.overlap), 0)
        c0, c1 = max(b0 - O, a), min(e + O, part.start + len(part.pen_before))
        say(f"seam frames {b0}-{e - 1}: {1000 * depth.max():.1f} mm deep after the cross-fade")
        seam.fixed = fitter.segment([(0, c0, c1)], 0, say, init=local, origin=a)
    return seam


def _apply_seams(joined: dict, seams: list) -> list[str]:
    """Write the seams' depths and their windows fitted again into ``joined`` (:func:`_join`'s dict),
    in place; returns those windows as ``"frames a-b"``."""
    mended = []
    for seam in seams:
        if seam is None:
            continue
        joined["pen_after"][seam.b0 : seam.e], joined["share_after"][seam.b0 : seam.e] = seam.depth, seam.share
        f = seam.fixed
        if f is not None:
            c0, c1 = f.start, f.start + len(f.pen_before)
            for key in ("delta", "dtransl", "opening"):
                for dst, src in zip(joined[key], getattr(f, key)):
                    dst[c0:c1] = src
            joined["pen_after"][c0:c1], joined["share_after"][c0:c1] = f.pen_after, f.share_after
            mended.append(f"frames {c0}-{c1 - 1}")
    return mended


class _Fitter:
    """Both actors' tensors and the collision term for one take: fits its segments
    (:func:`layout`), in this process or in a worker (:mod:`dualhuman_builder.fit.workers`)."""

    def __init__(self, model, inputs: list[ActorInput], fps: float, cfg: FitConfig, threads: int | None = None):
        """``threads``: the collision term's query threads (None: its default, the CPUs up to 8); worker
        processes build theirs with the same (:mod:`~dualhuman_builder.fit.workers`)."""
        from dualhuman_builder.geometry.collision import CollisionTerm
        from dualhuman_builder.fit.skeleton import sole_vertices, torso_vertices

        self.cfg, self.fps, self.T, self.threads = cfg, fps, len(inputs[0].seg_rot), threads
        soles = sole_vertices(model)
        slots = max(len(inp.trk_segment) for inp in inputs)
        self.acts = [_Actor(model, inp, fps, cfg, soles, slots) for inp in inputs]
        self.stack = _Stack(self.acts)
        #: ``(V,)`` bool: the vertices the hand openings move (one topology and skinning for both actors)
        self.fingers = self.acts[0].rig.opening_vertices
        self.dev = torch.device(cfg.device)
        # a 3 cm band (exact signed distances out to 3 cm; the broad-phase boxes still grow by 1 cm): the same
        # answers as the 1 cm default, but vertices keep a known sign over larger moves between L-BFGS
        # evaluations, so fewer need the sign flood fill (benchmarks/bench_fit_collision.py: 1.1-1.4x, identical depths)
        # the coincidence guard compares the torsos' centroids: the whole bodies' come within 2 cm in a close hug
        # the parts the sign bound takes one by one are each hand's fingers and the rest: the hands' pass moves the
        # fingers alone. With the body's 23 segments as parts too the checks and evaluations of a 0.15-minute hug,
        # replayed, took 10.1 s against 9.0 (medians of four; the segments' bound kept few more signs there)
        # the pooled meshes' trees are built over the first actor's rest pose, so that the answers do not
        # depend on which segments a process fitted before (CollisionTerm's bvh_points)
        self.collide = None
        if cfg.collision and len(self.acts) == 2:
            with torch.no_grad():
                eye = torch.eye(3, device=self.dev).expand(1, len(MVN_SEGMENTS), 3, 3)
                rest = self.acts[0].rig.pose(eye, torch.zeros(1, 3, device=self.dev), True).vertices[0].cpu().numpy()
            self.collide = CollisionTerm(model.faces.cpu().numpy(), band_m=0.03, pad_m=0.01,
                                         guard_vertices=torso_vertices(model), bvh_points=rest, threads=threads,
                                         parts=self.acts[0].rig.opening_groups)  # fmt: skip

    def segment(self, wins: list[tuple[int, int, int]], n_windows: int, say: Callable[[str], None],
                init: dict | None = None, origin: int = 0) -> _Part:  # fmt: skip
        """Fit the windows ``wins`` of one segment (:func:`layout`), the first from the retarget alone,
        each next from the one before; ``n_windows``: the take's count (for progress messages; 0:
        ``wins`` is a seam's window).
        ``init``: an answer so far (:func:`_join`'s dict; its row 0 is timeline frame ``origin``):
        then the first window starts from it, and the windows read its two frames before the first
        and after the last (as far as it reaches) as fixed context (a seam's window)."""
        acts, collide, dev, cfg, fps = self.acts, self.collide, self.dev, self.cfg, self.fps
        first, last = wins[0][1], wins[-1][2]
        a0, a1 = (first, last) if init is None else (max(first - 2, origin), min(last + 2, origin + len(init["delta"][0])))
        S = len(MVN_SEGMENTS)
        if init is None:
            deltas = [torch.zeros(a1 - a0, S, 3, device=dev) for _ in acts]
            dtransl = [torch.zeros(a1 - a0, 3, device=dev) for _ in acts]
            openings = [torch.zeros(a1 - a0, 4, device=dev) for _ in acts]
        else:
            deltas, dtransl, openings = ([torch.tensor(x[a0 - origin : a1 - origin], device=dev) for x in init[key]] for key in ("delta", "dtransl", "opening"))
        out = _Part(first, [], [], [], np.zeros(last - first), np.zeros(last - first))
        # per frame of the answer, the depth (m) and penetrating share of its current corrections where a check
        # measured them (nan: not measured), so that the answer's depths need no second measurement
        known = np.full((2, last - first), np.nan)
        if collide is not None:
            collide.clear_memo()  # each segment starts from the same state in any process
        P = 3  # optimised tensors per actor: delta, dtransl, opening
        for j_win, (wi, s0, s1) in enumerate(wins):
            sl = slice(s0, s1)  # timeline frames
            loc = slice(s0 - a0, s1 - a0)  # the same, in the segment's tensors
            ploc = slice(s0 - first, s1 - first)  # the same, in the answer's arrays
            ctx_n = min(2, s0 - a0) if (j_win or init is not None) else 0
            after_n = a1 - s1 if j_win == len(wins) - 1 else 0

            def context(k, a, csl):
                """(joints, soles, openings) of timeline frames ``csl`` from the segment's tensors."""
                cloc = slice(csl.start - a0, csl.stop - a0)
                return _context(a, deltas[k][cloc], dtransl[k][cloc], openings[k][cloc], csl)

            with torch.no_grad():
                ctxs = [context(k, a, slice(s0 - ctx_n, s0)) if ctx_n else None for k, a in enumerate(acts)]
                afters = [context(k, a, slice(s1, s1 + after_n)) if after_n else None for k, a in enumerate(acts)]
            params = []
            for k in range(len(acts)):
                params += [deltas[k][loc].clone().requires_grad_(True), dtransl[k][loc].clone().requires_grad_(True),
                           openings[k][loc].clone().requires_grad_(cfg.hand_opening)]
            # the skeleton pass moves the bones only (no term there reads the fingers); the collision passes
            # move the hands' openings too, when allowed (cbones, chands below)
            bones = [p for k in range(len(acts)) for p in params[P * k : P * k + 2]]

            def pose_all(ps, psl, idx):
                """Both actors' posed bodies, with vertices, at rows ``idx`` (a slice or index tensor) of the
                corrections ``ps`` (``P`` tensors per actor) of timeline frames ``psl``."""
                return [a.pose(ps[P * k][idx], ps[P * k + 1][idx], _rows(psl, idx), True, ps[P * k + 2][idx])[1]
                        for k, a in enumerate(acts)]  # fmt: skip

            def skeleton_energy(ps, psl, pctxs, pafters):
                """Both actors' skeleton energy (:func:`_energy`, at once) of the corrections ``ps`` of timeline
                frames ``psl``, and their driven bones' rotations (per actor, ``(n, 23, 3, 3)``)."""
                e, rot = _energy(self.stack, *(torch.stack(ps[j :: P]) for j in range(P)), psl, _stacked(pctxs), cfg, fps,
                                 _stacked(pafters))  # fmt: skip
                return e, rot.unbind(0)

            def held_rows(k, a, lo, hi):
                """(joints, soles, openings) of actor ``k``'s window rows ``lo .. hi - 1`` as they are now,
                without gradient (the context of a span of the window; None when empty)."""
                if hi <= lo:
                    return None
                with torch.no_grad():
                    return _context(a, *(params[P * k + j][lo:hi] for j in range(P)), slice(s0 + lo, s0 + hi))

            opt = torch.optim.LBFGS(bones, lr=1.0, max_iter=cfg.iterations, line_search_fn="strong_wolfe")

            def closure():
                opt.zero_grad()
                e, _ = skeleton_energy(params, sl, ctxs, afters)
                e.backward()
                return e

            opt.step(closure)
            if collide is not None:

                def check(ps=params, psl=sl, rows=None):
                    """The depths of timeline frames ``psl`` (only its rows ``rows``, sorted, when given) at the
                    corrections ``ps`` now (``penetration``'s dict, per row checked) and, when contacts are held,
                    them located (a :class:`_Located` the next held pass starts from; else None)."""
                    rows = np.arange(psl.stop - psl.start) if rows is None else np.asarray(rows)
                    with torch.no_grad():
                        idx = slice(None) if len(rows) == psl.stop - psl.start else torch.as_tensor(rows, device=dev)
                        vs = [p.vertices for p in pose_all(ps, psl, idx)]
                        keys = psl.start + rows
                        if not cfg.collision_hold_contacts:
                            return collide.penetration(vs[0], vs[1], keys=keys), None
                        lin = collide.linearise(vs[0], vs[1], keys=keys, margin_m=cfg.collision_margin_m)
                        return {"max_depth_m": lin.max_depth_m, "share": lin.share}, _Located(lin, rows)

                pen, located = check()
                out.pen_before[ploc] = pen["max_depth_m"]
                out.share_before[ploc] = pen["share"]
                known[:, ploc] = pen["max_depth_m"], pen["share"]
                hit = np.flatnonzero(pen["max_depth_m"] > 0)
                out.collided += len(hit)
                # the collision passes move the frames within `collision_span_s` of a hit frame (and those between,
                # window rows r0 .. r1 - 1: timeline frames c0 .. c1 - 1), the rest of the window held as it is,
                # its two frames on either side read as context: nothing moves elsewhere, so nothing new collides there
                r0, r1 = _span(hit, s1 - s0, cfg, fps)
                c0, c1, csl = s0 + r0, s0 + r1, slice(s0 + r0, s0 + r1)
                if (r0, r1) == (0, s1 - s0):
                    cparams, cctxs, cafters = params, ctxs, afters
                else:
                    cparams = [p[r0:r1].detach().clone().requires_grad_(p.requires_grad) for p in params]
                    cctxs = [_context_join(ctxs[k], held_rows(k, a, max(r0 - 2, 0), r0), last=True) for k, a in enumerate(acts)]
                    cafters = [_context_join(held_rows(k, a, r1, min(r1 + 2, s1 - s0)), afters[k], last=False) for k, a in enumerate(acts)]
                    if located is not None:
                        located = _Located(located.take(np.arange(r0, r1)), np.arange(r1 - r0))
                    pen = {key: pen[key][r0:r1] for key in ("max_depth_m", "share")}
                    hit = hit - r0
                cbones = [p for k in range(len(acts)) for p in cparams[P * k : P * k + 2]]
                chands = [cparams[P * k + 2] for k in range(len(acts))] if cfg.hand_opening else []
                # (the deepest frame's depth, the corrections, the per-frame depths and penetrating shares (c1 - c0,)
                # each, and the contacts located there or None) after the skeleton pass; `best` below: the same after
                # the best round so far (a round undone goes back to it without locating its contacts again)
                start = (float(pen["max_depth_m"].max()), [p.detach().clone() for p in cparams], pen["max_depth_m"], pen["share"],
                         located)  # fmt: skip
                # the hands first: their openings have no data term, so they give way before any bone the
                # suit and trackers hold, and the full rounds start from hands that already fit
                passes = (["hands"] if chands else []) + ["all"] * max(int(cfg.collision_rounds), 1)
                # held contacts first (cheap evaluations), except in the frames where a held round stalled: from then
                # on those are located at every evaluation. A window the held rounds leave unsettled is fitted again
                # from its skeleton pass with those frames and the ones left too deep located at every evaluation,
                # and keeps the better answer
                modes = ["held", "exact"] if cfg.collision_hold_contacts else ["exact"]
                # rows of the span whose contacts are located at every evaluation
                exact = np.zeros(0, np.int64) if cfg.collision_hold_contacts else np.arange(c1 - c0)
                best, held_best = start, None
                energies = None  # (after the skeleton pass, after the held rounds) where they settled after a stall

                def skel_e(ps):
                    """The skeleton energy (every term but the collision term) of the span at corrections ``ps``."""
                    with torch.no_grad():
                        return float(skeleton_energy(ps, csl, cctxs, cafters)[0])

                for mode in modes if len(hit) else []:
                    best, restarts, settled = start, 0, False
                    hit = np.flatnonzero(start[2] > 0)
                    if mode == "exact" and len(modes) == 2:
                        # exact in the frames the held rounds located exactly and those they left over the
                        # tolerance (the accuracy benchmark's dance turns: 24 and 19 s instead of 38 and 26 with all
                        # of them, in a sweep with a script outside the repo)
                        exact = np.union1d(exact, np.flatnonzero(held_best[2] > cfg.collision_tolerance_m))
                        _restore(cparams, start[1])
                        out.exact_windows.append(f"frames {c0}-{c1 - 1}")
                        located = start[4]
                    n_round = 0  # the full rounds count from 1 (the hands' pass: 0)
                    for i_pass, what in enumerate(passes):
                        n_round += what == "all"
                        weight = cfg.collision_weight * cfg.collision_weight_step ** i_pass  # the hands' pass included
                        if i_pass == 0:  # per row of the span, the weight's multiple (collision_deep_m)
                            ahead = np.ones(c1 - c0)
                        if what == "all" and n_round == 1 and cfg.collision_deep_m > 0:
                            ahead = np.where(best[2] > cfg.collision_deep_m, cfg.collision_weight_step, 1.0)
                        if i_pass == 0:  # span rows this pass moves: all in the first; then see collision_hold_settled
                            moving = np.ones(c1 - c0, bool)
                        elif what == "all" and cfg.collision_hold_settled:
                            over = (best[2] > cfg.collision_tolerance_m) | (best[3] > cfg.collision_share_tolerance)
                            if not over.any():
                                # the best answer is within the tolerances already: the skeleton pass left only
                                # shallow contacts and the pass after it was undone (deeper); nothing to move
                                settled = True
                                break
                            # (frames held so far kept the depths that let them be held, so `over` lies in `moving`)
                            moving = moving & _dilate(over, _SMOOTH_REACH)
                        rows_m = np.flatnonzero(moving)
                        frozen_t = None if moving.all() else torch.as_tensor(np.flatnonzero(~moving), device=dev)
                        phit = hit[moving[hit]]  # the hit rows that move (a held row's term is a constant)
                        hit_t = torch.as_tensor(phit, device=dev)
                        start_left = best[2]  # the span's depths at the start of this pass (it starts from the best)
                        free = chands if what == "hands" else cbones + chands
                        copt = torch.optim.LBFGS(free, lr=1.0, max_iter=cfg.collision_iterations, line_search_fn="strong_wolfe")
                        label = f"frames {c0}-{c1 - 1}, " + ("the hands' collision pass" if what == "hands" else f"collision round {n_round}")
                        # rows of `phit` whose contacts are held, and those located at every evaluation
                        rows_x = np.flatnonzero(np.isin(phit, exact))
                        rows_h = np.setdiff1d(np.arange(len(phit)), rows_x)
                        use_held = len(rows_h) > 0
                        label += ", held contacts" if len(rows_x) == 0 else (f", exact at {len(rows_x)} frames" if use_held else "")
                        held = None
                        if use_held:  # located where the pass starts (by the last check, if the bodies are still there)
                            if located is None:
                                _, located = check(cparams, csl, rows_m)
                            held = located.take(phit[rows_h])
                        # the hands' pass moves the openings alone: the bones' rotations and positions are constants
                        # there (no gradient, no skeleton terms but the openings', _opening_energy), and so are the
                        # depths of the held contacts that touch no finger
                        fixed = None
                        if what == "hands":
                            with torch.no_grad():
                                fixed = self.stack.rotations(torch.stack(cparams[0::P]), csl).unbind(0)
                            if held is not None:
                                held = collide.moving_only(held, self.fingers)

                        ahead_h, ahead_x = (torch.as_tensor(ahead[phit[r]], dtype=cparams[0].dtype, device=dev) for r in (rows_h, rows_x))

                        def cclosure(phit=phit, hit_t=hit_t, weight=weight, copt=copt, held=held, rows_h=rows_h,
                                     rows_x=rows_x, fixed=fixed, ahead_h=ahead_h, ahead_x=ahead_x, frozen_t=frozen_t):  # fmt: skip
                            if not _finite(cparams):
                                raise _Diverged
                            copt.zero_grad()
                            if fixed is None:
                                e, rots = skeleton_energy(cparams, csl, cctxs, cafters)
                                transl = [cparams[P * k + 1] for k in range(len(acts))]
                            else:
                                e = _opening_energy(torch.stack(cparams[2::P]), _stacked(cctxs), _stacked(cafters), cfg, fps)
                                rots, transl = fixed, [cparams[P * k + 1].detach() for k in range(len(acts))]
                            # every bone of the hit frames (fingers opened), for the few thousand (frame, vertex)
                            # pairs the loss reads, skinned with the gradient
                            # (index_select: its backward is an index_add, cheaper than indexing's index_put)
                            posed_hit = [a.rig.pose(rots[k].index_select(0, hit_t), a.transl0[c0 + hit_t] + transl[k].index_select(0, hit_t),
                                                    False, cparams[P * k + 2].index_select(0, hit_t)) for k, a in enumerate(acts)]  # fmt: skip

                            def at(rows):  # the collision term's batch rows are `rows` of `phit`
                                rows = torch.as_tensor(rows, device=dev)
                                return lambda body, f, v: acts[body].rig.skin_at(posed_hit[body], rows[f], v)

                            c = 0.0
                            if held is not None:
                                c = c + (ahead_h * collide.linear_loss(held, at(rows_h), device=dev)).sum()
                            if len(rows_x):  # the full meshes, without gradient, locate the contacts
                                with torch.no_grad():
                                    vs = [p.vertices for p in pose_all(cparams, csl, hit_t[rows_x])]
                                c = c + (ahead_x * collide(vs[0], vs[1], keys=c0 + phit[rows_x], points=at(rows_x)).loss).sum()
                            e = e + weight * c
                            e.backward()
                            if frozen_t is not None:  # the rows this pass holds: no step (L-BFGS keeps them where they are)
                                for q in cparams:
                                    if q.grad is not None:
                                        q.grad.index_fill_(0, frozen_t, 0.0)
                            return e

                        located = None  # the bodies move
                        try:
                            copt.step(cclosure)
                        except _Diverged:
                            pass
                        if not _finite(cparams):
                            # the line search stepped to non-finite corrections: keep the best round's answer
                            _restore(cparams, best[1])
                            out.diverged.append(label)
                            break
                        # how deep one pass leaves a frame depends on where it started, so frames still deeper than
                        # the tolerance go round again with the term weighted up. Every frame that was ever hit keeps
                        # the term: released, it would spring back (the other terms still pull it in) while its
                        # neighbours are refitted. Frames pushed into contact by their neighbours join.
                        now_pen, located = check(cparams, csl, rows_m)
                        if frozen_t is not None:  # the rows held are where the pass started (the best answer): its depths
                            for key, was in (("max_depth_m", best[2]), ("share", best[3])):
                                full = np.array(was, dtype=float)
                                full[rows_m] = now_pen[key]
                                now_pen[key] = full
                        left = now_pen["max_depth_m"]
                        if what == "all":  # the summary counts the full rounds (the hands' pass is extra)
                            out.rounds = max(out.rounds, n_round)
                        stall = max(cfg.collision_tolerance_m, 0.75 * start_left.max())
                        if use_held and what == "all" and left.max() > stall:
                            # held planes stall where the answer lies through a thin part of the partner (a hand
                            # 2 cm into a forearm: the exact term pushes it on through and out of the far side
                            # once it passes the middle; a held plane holds the near side) or where the closest
                            # faces change as the bodies move (interlocked fingers): the frames left that deep are
                            # located at every evaluation from now on
                            new = np.setdiff1d(np.flatnonzero(left > stall), exact)
                            exact = np.union1d(exact, new)
                            out.stalled.append(label)
                            out.exact_frames += [int(c0 + f) for f in new]
                        if left.max() > best[0]:
                            # deeper than the best round so far (the data pull the bodies into each other harder
                            # than the term can hold them apart, and L-BFGS stepped into a worse basin): undo it;
                            # the next round starts again from the best answer, with the term weighted up
                            _restore(cparams, best[1])
                            located = best[4]
                            out.worsened.append(f"{label}: {1000 * left.max():.1f} mm after, {1000 * best[0]:.1f} mm before")
                        else:
                            best = (float(left.max()), [p.detach().clone() for p in cparams], left, now_pen["share"], located)
                            if _settled(left, now_pen["share"], cfg):
                                settled = True
                                break
                        hit = np.union1d(hit, np.flatnonzero(left > 0))
                        if what == "all" and cfg.collision_restart and restarts < _MAX_RESTARTS and n_round >= 2:
                            # frames a round could not move (interlocked hands: the two pushes oppose each other)
                            # start again from their neighbours' answer, where the bodies meet less deeply. The
                            # window now holds the best answer (kept or restored), and the round started from the
                            # best before it: compare those two
                            now = best[2]
                            deep = now > cfg.collision_tolerance_m
                            stuck = deep & (now > 0.8 * start_left)
                            if stuck.any():  # each run of deep frames holding a stuck one, from the clean frames around it
                                run = np.cumsum(np.r_[True, deep[1:] != deep[:-1]])
                                if _restart_from_neighbours(cparams, deep & np.isin(run, run[stuck])):
                                    restarts += 1
                                    located = None
                                    say(f"{label}: {int(stuck.sum())} frames stuck, restarted from their neighbours")
                    if mode == "held" and settled and len(modes) == 2 and len(exact) and cfg.collision_energy_ratio > 0:
                        # settled after a stall: was the shape bent to get there? (collision_energy_ratio)
                        energies = max(skel_e(start[1]), 1e-12), skel_e(best[1])  # (an energy of 0: no division by it)
                        if energies[1] > cfg.collision_energy_ratio * energies[0]:
                            settled = False
                            say(f"frames {c0}-{c1 - 1}: the held rounds settled with the skeleton energy {energies[1] / energies[0]:.1f}x "
                                "the skeleton pass's; fitted again the exact way")  # fmt: skip
                    if settled or mode == "exact":
                        break
                    held_best = best
                if held_best is not None:
                    if energies is not None and _settled(best[2], best[3], cfg):  # both settled (the energy's refit): the lower energy
                        (e_start, e_held), e_exact = energies, skel_e(best[1])
                        keep_held = e_held <= e_exact
                        out.energy_refits.append(f"frames {c0}-{c1 - 1}: skeleton energy {e_held / e_start:.2f}x the skeleton pass's held, "
                                                 f"{e_exact / e_start:.2f}x exact; kept {'held' if keep_held else 'exact'}")  # fmt: skip
                    else:
                        keep_held = held_best[0] < best[0]  # the held rounds had left it less deep
                    if keep_held:
                        _restore(cparams, held_best[1])
                # the span's answer is one a check measured (the best round's, the held rounds' best or the skeleton
                # pass's) unless a restart in the last round moved it since: then the end of the segment measures it
                span = slice(ploc.start + r0, ploc.start + r1)
                known[:, span] = np.nan
                for snap in (best, held_best):
                    if snap is not None and all(torch.equal(p, q) for p, q in zip(cparams, snap[1])):
                        known[:, span] = snap[2], snap[3]
                        break
                if cparams is not params:
                    with torch.no_grad():
                        for p, q in zip(params, cparams):
                            p[r0:r1] = q
            for k in range(len(acts)):  # overlapping frames take the later window's answer
                for j, t in enumerate((deltas[k], dtransl[k], openings[k])):
                    t[loc] = params[P * k + j].detach()
            say(f"window {wi + 1}/{n_windows}: frames {s0}-{s1 - 1}" if n_windows else f"seam: frames {s0}-{s1 - 1} fitted again")
        out.delta, out.dtransl, out.opening = ([x[first - a0 : last - a0].cpu().numpy() for x in xs] for xs in (deltas, dtransl, openings))
        if collide is not None:  # how deep the answer leaves each frame (measured here where no check did)
            out.pen_after, out.share_after = known
            for a, b in _runs(np.isnan(known[0])):
                out.pen_after[a:b], out.share_after[a:b] = self.depths(first + a, first + b, deltas, dtransl, openings, origin=a0)
        return out

    def depths(self, s0: int, s1: int, delta: list, dtransl: list, opening: list, origin: int) -> tuple[np.ndarray, np.ndarray]:
        """The deepest vertex (m) and the penetrating share of timeline frames ``s0 .. s1 - 1`` ``(n,)``
        each, for per-actor corrections ``delta``/``dtransl``/``opening`` (arrays or tensors whose row
        0 is timeline frame ``origin``), 64 frames at a time."""
        depth, share = np.zeros(s1 - s0), np.zeros(s1 - s0)
        for c0 in range(s0, s1, 64):
            sl = slice(c0, min(c0 + 64, s1))
            rows = slice(sl.start - origin, sl.stop - origin)
            with torch.no_grad():
                vs = [a.pose(*(torch.as_tensor(x[k][rows], device=self.dev) for x in (delta, dtransl)), sl, True,
                             torch.as_tensor(opening[k][rows], device=self.dev))[1].vertices for k, a in enumerate(self.acts)]  # fmt: skip
                pen = self.collide.penetration(vs[0], vs[1], keys=range(sl.start, sl.stop))
            depth[sl.start - s0 : sl.stop - s0] = pen["max_depth_m"]
            share[sl.start - s0 : sl.stop - s0] = pen["share"]
        return depth, share


def _fit_actors(model, inputs: list[ActorInput], fps: float, cfg: FitConfig, progress, workers: int | None) -> FitResult:
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    say = progress or (lambda _m: None)
    if not inputs:
        raise FitError("nothing to fit: no actors")
    T = len(inputs[0].seg_rot)
    if any(len(i.seg_rot) != T for i in inputs):
        raise FitError("actors have different frame counts; run them through one sync")
    if T < 2:
        raise FitError(f"the take has {T} frame(s) on the timeline; fitting needs at least 2")
    t_start = time.perf_counter()
    segments = layout(T, cfg)
    n_windows = sum(len(seg) for seg in segments)
    n_workers = fit_workers(len(segments), cfg) if workers is None else max(1, min(int(workers), len(segments)))
    if n_workers > 1 and not _workers_build_it(model):
        say(f"fit: {n_workers} workers asked for, but the body model is not the toolkit's float32 anny; fitting in this process")
        n_workers = 1
    fitter = _Fitter(model, inputs, fps, cfg, threads=collision_threads(n_workers))
    acts, collide, dev = fitter.acts, fitter.collide, fitter.dev
    if n_workers > 1:
        from dualhuman_builder.fit.workers import fit_in_workers

        say(f"fit: {len(segments)} segments of up to {max(1, int(cfg.segment_windows))} windows, on {n_workers} processes")
        parts, seams_done, worker_mb = fit_in_workers(fitter, inputs, fps, segments, n_windows, n_workers, say)
    else:
        parts = [fitter.segment(seg, n_windows, say) for seg in segments]
        seams_done, worker_mb = [_seam(fitter, p, q, say) for p, q in zip(parts, parts[1:])], None
    joined = _join(parts, T)
    seams = _apply_seams(joined, seams_done)
    deltas, dtransl, openings = ([torch.as_tensor(x, device=dev) for x in joined[key]] for key in ("delta", "dtransl", "opening"))
    pen_before, pen_share_before = joined["pen_before"], joined["share_before"]
    pen_after, share_after = joined["pen_after"], joined["share_after"]
    # the seams' windows fitted again count with the segments (a pass there can diverge or stall too)
    fitted = parts + [s.fixed for s in seams_done if s is not None and s.fixed is not None]
    collided_frames = sum(p.collided for p in fitted)
    rounds_used = max(p.rounds for p in fitted)
    diverged = [x for p in fitted for x in p.diverged]
    worsened = [x for p in fitted for x in p.worsened]
    exact_frames = [x for p in fitted for x in p.exact_frames]
    exact_windows = [x for p in fitted for x in p.exact_windows]
    stalled_rounds = [x for p in fitted for x in p.stalled]
    energy_refits = [x for p in fitted for x in p.energy_refits]

    # ---- outputs and per-frame diagnostics
    tracks, frames = [], {}
    for k, a in enumerate(acts):
        with torch.no_grad():
            rot = a.rotations(deltas[k], slice(None))
            transl = a.transl0 + dtransl[k]
            pose = a.rig.local_pose(rot, openings[k]).cpu().numpy()
            ang = np.degrees(deltas[k].norm(dim=-1).mean(-1).cpu().numpy())
            frames[f"orientation change (deg)/{a.name}"] = np.where(a.valid.cpu().numpy(), ang, np.nan)
            o = openings[k]  # per frame the opening farthest from relaxed, with its sign (< 0: curled)
            frames[f"hand opening (0 relaxed, 1 flat)/{a.name}"] = o.gather(1, o.abs().argmax(1, keepdim=True))[:, 0].cpu().numpy()
            if len(a.trk_seg):
                posed = a.rig.pose(rot, transl, False)
                seg_frame = rot[:, a.trk_seg] @ a.rig.seg_frame[a.trk_seg]
                site = posed.heads[:, a.trk_bone] + (seg_frame @ a.trk_off[None, :, :, None])[..., 0]
                r = (site - a.trk_pos).norm(dim=-1).cpu().numpy() * 1000
                tv = a.trk_valid.cpu().numpy()
                with np.errstate(invalid="ignore"):
                    frames[f"tracker residual (mm)/{a.name}"] = np.where(tv.any(1), (r * tv).sum(1) / np.maximum(tv.sum(1), 1), np.nan)
        shape = a.rig.shape.cpu().numpy()
        meta = {"fit": {"collision": collide is not None, "trackers": int(len(a.trk_seg)), "config": _config_dict(cfg)}}
        tracks.append(BodyTrack.from_model(model, pose, transl.cpu().numpy(), shape, fps, actor=a.name, meta=meta))
    if collide is not None:
        frames["penetration depth (mm)/without collision term"] = pen_before * 1000
        frames["penetration depth (mm)/with collision term"] = pen_after * 1000
    valid = np.logical_and.reduce([a.valid.cpu().numpy() for a in acts])
    seq = InteractionSequence(tuple(tracks)) if len(tracks) == 2 else None
    seconds = time.perf_counter() - t_start  # everything: the segments, the seams, the outputs and diagnostics
    summary = {"frames": T, "fit_seconds": round(seconds, 3), "frame_pairs_per_s": round(T / max(seconds, 1e-9), 2),
               "collision_frames": int(collided_frames), "collision_rounds_used": int(rounds_used),
               "collision_diverged": diverged, "collision_worsened": worsened,
               "collision_exact_frames": exact_frames, "collision_exact_windows": exact_windows, "collision_held_stalled": stalled_rounds,
               "collision_energy_refits": energy_refits,
               "segments": len(segments), "processes": n_workers, "seams_fitted_again": seams,
               "worker_peak_rss_mb": None if worker_mb is None else round(worker_mb)}  # fmt: skip
    if collide is not None:
        summary.update(max_penetration_before_mm=round(float(pen_before.max() * 1000), 3),
                       max_penetration_after_mm=round(float(pen_after.max() * 1000), 3),
                       penetrating_share_before=float(pen_share_before.max()), penetrating_share_after=float(share_after.max()))  # fmt: skip
    return FitResult(seq if seq is not None else tracks, frames, summary, valid)


def _restart_from_neighbours(params, stuck: np.ndarray) -> bool:
    """Set every run of ``stuck (W,)`` frames of the window's ``params`` (each ``(W, ...)``) to the
    linear interpolation between the frames just before and after it (the one there is at the
    window's edge). False when every frame is stuck (no neighbour to start from)."""
    W = len(stuck)
    if stuck.all():
        return False
    with torch.no_grad():
        for a, b in _runs(stuck):  # frames a .. b-1
            lo, hi = a - 1, b
            for p in params:
                if lo < 0:
                    p[a:b] = p[hi]
                elif hi >= W:
                    p[a:b] = p[lo]
                else:
                    w = torch.linspace(0.0, 1.0, b - a + 2, dtype=p.dtype, device=p.device)[1:-1]
                    w = w.reshape(-1, *([1] * (p.dim() - 1)))
                    p[a:b] = (1 - w) * p[lo] + w * p[hi]
    return True


def _dilate(mask: np.ndarray, n: int) -> np.ndarray:
    """``(W,)`` bool: the rows within ``n`` rows of a True row of ``mask (W,)``."""
    c = np.r_[0, np.cumsum(mask, dtype=np.int64)]
    i = np.arange(len(mask))
    return c[np.minimum(i + n + 1, len(mask))] - c[np.maximum(i - n, 0)] > 0


@dataclass
class _Located:
    """Contacts located at some rows of a window's span: ``lin`` (a
    :class:`~dualhuman_builder.geometry.collision.Linearised`) whose batch rows are the span rows ``rows``
    (sorted)."""

    lin: object
    rows: np.ndarray

    def take(self, rows) -> object:
        """The contacts of span rows ``rows`` (each located here), renumbered ``0 .. len(rows) - 1``."""
        rows = np.asarray(rows, np.int64)
        at = np.minimum(np.searchsorted(self.rows, rows), max(len(self.rows) - 1, 0))
        if len(rows) and not np.array_equal(self.rows[at], rows):
            raise RuntimeError(f"span rows {np.setdiff1d(rows, self.rows).tolist()} were not located")
        return self.lin.subset(at)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """The runs of True in ``mask (n,)``, as ``(first, end)`` index pairs."""
    edges = np.flatnonzero(np.diff(np.r_[0, mask.astype(np.int8), 0]))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2])]


def _span(hit: np.ndarray, W: int, cfg: FitConfig, fps: float) -> tuple[int, int]:
    """Window rows ``r0 .. r1 - 1`` the collision passes of a ``W``-frame window move, for its hit frames
    ``hit`` (rows, sorted): from ``cfg.collision_span_s`` before the first to as long after the last
    (the whole window when that is 0 or there is no hit)."""
    if not len(hit) or cfg.collision_span_s <= 0:
        return 0, W
    n = int(np.ceil(cfg.collision_span_s * fps))
    return max(int(hit[0]) - n, 0), min(int(hit[-1]) + 1 + n, W)


def _context(act: _Actor, delta, dtransl, opening, sl: slice) -> tuple:
    """What :func:`_energy` reads of fixed frames around the ones it fits: (joints ``(n, 22, 3)``,
    sole vertices ``(n, 2 n_sole, 3)``, openings ``(n, 4)``) of timeline frames ``sl`` with the
    corrections ``delta``/``dtransl``/``opening`` (call it without gradient)."""
    rot = act.rotations(delta, sl)
    (joints, _, _), sole = act.skeleton(rot, act.transl0[sl] + dtransl)
    return joints, sole, opening


def _stacked(ctxs: list):
    """Per-actor contexts (each (joints, soles, openings), all of one length, or all None) as one with the
    actors' axis first, for :func:`_energy`; None when they are None."""
    if ctxs[0] is None:
        return None
    return tuple(torch.stack([c[i] for c in ctxs]) for i in range(3))


def _context_join(a, b, last: bool):
    """Two consecutive (joints, soles, openings) contexts (either None) as one, cut to its last two
    frames (``last``) or its first two; None when both are None."""
    parts = [x for x in (a, b) if x is not None]
    if not parts:
        return None
    cut = slice(-2, None) if last else slice(0, 2)
    return tuple(torch.cat([x[i] for x in parts], 0)[cut] for i in range(3))


def _rows(sl: slice, idx):
    """Timeline frames of window rows ``idx`` (a slice of the window or an index tensor)."""
    if isinstance(idx, slice):
        return slice(sl.start + (idx.start or 0), sl.start + (idx.stop if idx.stop is not None else sl.stop - sl.start))
    return sl.start + idx


def _config_dict(cfg: FitConfig) -> dict:
    return {k: getattr(cfg, k) for k in cfg.__dataclass_fields__}


def inputs_from_fused(fused: list, shapes: dict[str, dict]) -> list[ActorInput]:
    """:class:`ActorInput` per :class:`~dualhuman_builder.fit.fuse.FusedActor`."""
    out = []
    lf, rf = MVN_SEGMENTS.index("LeftFoot"), MVN_SEGMENTS.index("RightFoot")
    for f in fused:
        sk = f.skeleton
        valid = np.asarray(sk.orientation_valid).all(1)
        out.append(ActorInput(name=sk.actor, shape=shapes[sk.actor], seg_rot=np.asarray(sk.orientations),
                              pelvis=np.asarray(sk.positions[:, 0]), valid=valid, trk_pos=f.trk_pos, trk_valid=f.trk_valid,
                              trk_segment=f.trk_segment, trk_offset=f.trk_offset,
                              ankles=np.asarray(sk.positions[:, [lf, rf]])))  # fmt: skip
    return out


__all__ = ["FitConfig", "FitError", "FitResult", "ActorInput", "fit_actors", "inputs_from_fused"]

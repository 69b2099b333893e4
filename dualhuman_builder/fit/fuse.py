"""Fuse stage: per actor, one drift-free skeleton from the suit's orientations and the trackers.

The trackers are the reference: the sync stage solved each tracker's mount on its segment and the
suit's heading ``psi(t)`` and position drift ``d(t)`` against the tracker world
(:func:`~dualhuman_builder.sync.mount.calibrate_mounts`). Fusion applies them to every segment::

    R'(t) = Y(psi(t)) R_suit(t) exp(-[eps]x)        p'(t) = Y(psi(t)) p_suit(t) + d(t)

where ``eps`` is each segment's constant misalignment solved with the mounts along the chains from
the pelvis to the trackers (:class:`~dualhuman_builder.sync.mount.SuitChain`; zero elsewhere), and
each tracker's offset solved in the measured frame is turned into the corrected one
(``exp([eps]x) m``). Then fusion pulls each tracked segment onto its tracker (origin
``p_tr - R' m``): the correction is kept where the tracker is valid, bridged linearly across
dropouts (no jump when a tracker comes back) and held at the edges. Tracker samples that disagree with the suit by more than
:data:`JUMP_M` (a tracker that lost tracking and reports the origin, or a swapped tracker) are
rejected, as are those the mount calibration flagged.

Without trackers (none in the rig, or ``--no-trackers``) the suit's own positions are used and the
result is flagged ``fused_with_trackers = False``: the suit's position drift then remains.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.tracks import SkeletonTrack

#: A tracker-implied segment origin this far (m) from the drift-corrected suit's is rejected.
JUMP_M = 0.15


@dataclass
class FusedActor:
    """One actor on the timeline (``T`` frames).

    ``skeleton``: the fused :class:`SkeletonTrack` (23 MVN segments, tracker world);
    ``trk_pos (T, K, 3)`` tracker positions, ``trk_valid (T, K)`` after rejection,
    ``trk_segment (K,)`` MVN segment index, ``trk_offset (K, 3)`` tracker origin in its segment's
    frame (m); ``fused_with_trackers``; ``stats``: counts of rejected / bridged samples per tracker.
    """

    skeleton: SkeletonTrack
    serials: tuple[str, ...]
    trk_pos: np.ndarray
    trk_valid: np.ndarray
    trk_segment: np.ndarray
    trk_offset: np.ndarray
    fused_with_trackers: bool
    stats: dict


def bridge_rows(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill invalid rows of ``values (T, 3)`` by linear interpolation between valid ones (held at
    the ends); all-invalid gives zeros."""
    if not valid.any():
        return np.zeros_like(values)
    t = np.arange(len(values))
    return np.stack([np.interp(t, t[valid], values[valid, i]) for i in range(values.shape[1])], axis=1)


def fuse_actor(streams, times_s: np.ndarray, fps: float) -> FusedActor:
    """Fuse one :class:`~dualhuman_builder.sync.timeline.ActorStreams` (see the module docstring)."""
    rot = np.asarray(streams.suit_rot, dtype=np.float64)
    pos = np.asarray(streams.suit_pos, dtype=np.float64)
    valid = np.asarray(streams.suit_valid, bool).copy()
    T, S = rot.shape[:2]
    mounts = streams.mounts
    K = len(streams.serials)
    stats: dict = {}
    if K == 0 or mounts is None or not np.any(mounts.calibrated):
        nanrot = np.where(valid[:, None, None], rot, np.array([0.0, 0.0, 0.0, 1.0]))
        sk = SkeletonTrack(MVN_SEGMENTS, nanrot, np.where(valid[:, None, None], pos, 0.0), _ns(times_s), _ns(times_s),
                           actor=streams.actor, fps=fps, orientation_valid=np.repeat(valid[:, None], S, 1),
                           position_valid=np.repeat(valid[:, None], S, 1),
                           meta={"fused_with_trackers": False})  # fmt: skip
        return FusedActor(sk, (), np.zeros((T, 0, 3)), np.zeros((T, 0), bool), np.zeros(0, np.int64), np.zeros((0, 3)), False, stats)

    yaw = Rotation.from_rotvec(np.outer(np.nan_to_num(mounts.heading_rad), [0.0, 1.0, 0.0]))
    q = np.where(valid[:, None, None], rot, np.array([0.0, 0.0, 0.0, 1.0]))
    r_suit = Rotation.from_quat(q.reshape(-1, 4))
    r_fused = Rotation.from_quat(np.repeat(yaw.as_quat(), S, axis=0)) * r_suit
    # the suit's segment misalignments solved with the mounts: R_true = R_meas exp(-[eps]x)
    misalign = chain_corrections(mounts, S)
    if np.any(misalign):
        r_fused = r_fused * Rotation.from_rotvec(np.tile(-misalign, (T, 1)))
    p_fused = np.empty((T, S, 3))
    for s in range(S):
        p_fused[:, s] = yaw.apply(np.where(valid[:, None], pos[:, s], 0.0)) + np.nan_to_num(mounts.drift)
    r_fused_m = r_fused.as_matrix().reshape(T, S, 3, 3)

    seg_idx = np.array([MVN_SEGMENTS.index(g) for g in streams.segments], dtype=np.int64)
    trk_valid = np.asarray(streams.trk_valid, bool) & valid[:, None] & ~np.asarray(mounts.outliers, bool)
    trk_valid &= np.asarray(mounts.calibrated, bool)[None, :]
    trk_pos = np.asarray(streams.trk_pos, dtype=np.float64)
    offsets = np.nan_to_num(np.asarray(mounts.translations, dtype=np.float64))
    # an offset solved in the measured frame, in the corrected one: R_meas m = R_true exp([eps]x) m
    offsets = Rotation.from_rotvec(misalign[seg_idx]).apply(offsets)
    for k in range(K):
        s = seg_idx[k]
        implied = trk_pos[:, k] - np.einsum("tij,j->ti", r_fused_m[:, s], offsets[k])
        delta = implied - p_fused[:, s]
        jump = ~(np.linalg.norm(np.nan_to_num(delta, nan=1e9), axis=1) < JUMP_M)
        rejected = trk_valid[:, k] & jump
        trk_valid[:, k] &= ~jump
        corr = bridge_rows(np.nan_to_num(delta), trk_valid[:, k])
        # the correction moves the segment and everything below it in the chain would need FK; the
        # fused skeleton moves only the tracked segment's origin (the fitter solves the chain)
        p_fused[:, s] += corr
        stats[streams.serials[k]] = {"valid_frames": int(trk_valid[:, k].sum()), "rejected_jumps": int(rejected.sum()),
                                     "bridged_frames": int((~trk_valid[:, k] & valid).sum())}  # fmt: skip
    quat = r_fused.as_quat().reshape(T, S, 4)
    vmask = np.repeat(valid[:, None], S, 1)
    sk = SkeletonTrack(MVN_SEGMENTS, quat, p_fused, _ns(times_s), _ns(times_s), actor=streams.actor, fps=fps,
                       orientation_valid=vmask, position_valid=vmask, meta={"fused_with_trackers": True})  # fmt: skip
    return FusedActor(sk, tuple(streams.serials), np.where(trk_valid[..., None], trk_pos, np.nan), trk_valid, seg_idx,
                      offsets, True, stats)  # fmt: skip


def chain_corrections(mounts, num_segments: int) -> np.ndarray:
    """``(S, 3)`` rotation vectors (rad): each suit segment's misalignment ``eps`` solved with the
    mounts (:class:`~dualhuman_builder.sync.mount.SuitChain`), zero where none was solved."""
    out = np.zeros((num_segments, 3))
    segs = np.asarray(getattr(mounts, "chain_segments", np.zeros(0)), np.int64)
    if segs.size:
        out[segs] = np.nan_to_num(np.asarray(mounts.chain_misalignment_rad, np.float64))
    return out


def _ns(times_s: np.ndarray) -> np.ndarray:
    return np.round(np.asarray(times_s) * 1e9).astype(np.int64)

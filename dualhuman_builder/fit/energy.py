"""The fit's skeleton energy: every term but the collision term, for both actors at once.

Per window of ``n`` frames, with ``A`` actors stacked (:class:`~dualhuman_builder.fit.actors.ActorStack`)::

    E = sum_frames [ w_s |delta_s|^2 / s_o^2                    orientation: change of each driven bone
                   + sum_trackers |site - p_tracker|^2 / s_t^2  tracker positions (drift-free reference)
                   + sum_joints |accel|^2 / s_a^2               temporal smoothness (22 joints)
                   + sum_soles relu(-y)^2 / s_f^2               no foot below the floor
                   + sum_stance (min_sole y)^2 / s_c^2          a foot in stance stands on it
                   + sum_stance |sole step|^2 / s_s^2           no sliding while a foot is in stance
                   + sum_hands (o / s_h)^2 + |o''|^2 / s_ha^2   hand openings: relaxed unless pushed ]

``delta (A, n, 23, 3)`` rotation vectors (rad), ``dtransl (A, n, 3)`` (m), ``opening (A, n, 4)`` (0
anny's relaxed hand, 1 flat; :mod:`dualhuman_builder.body.hands`); ``w_s`` the trust in segment ``s``'s
measured orientation (1; :data:`~dualhuman_builder.fit.actors.UNMEASURED_WEIGHT` where no sensor measured
it, an upper-body recording's legs); the sigmas are
:class:`~dualhuman_builder.fit.config.FitConfig`'s. The bones' terms read only ~30 bone heads and ~80
sole vertices per actor, linear in the driven rotations (:meth:`BodyRig.pose_linear`), so no mesh is
skinned here. The smoothness terms read up to two fixed frames on either side of the window: a
*context* ``(joints (A, m, 22, 3), soles (A, m, 2 n_sole, 3), openings (A, m, 4))``, ``m <= 2``.
"""

from __future__ import annotations

import numpy as np
import torch

from dualhuman_builder.fit.actors import ActorStack, ActorTensors
from dualhuman_builder.fit.config import FitConfig

#: the range the hand openings are held in (soft walls): a little more curled than relaxed, to flat
OPENING_RANGE = (-0.5, 1.0)


def summer(n: int | None):
    """How :func:`skeleton_energy` reduces a term ``(A, m, ...)`` whose rows are frames ``first .. first
    + m - 1`` of the ``n`` fitted: summed to a 0-d tensor (``n`` None), or per frame ``(n,)`` (actors
    summed; a term over several frames counts to the one ``first`` names: a second difference to its
    middle frame, a step to its later frame, so that each reads only frames within one of its own)."""
    if n is None:
        return lambda x, first=0: x.sum()

    def per_frame(x, first=0):
        v = x.reshape(x.shape[0], x.shape[1], -1).sum((0, 2))
        return torch.nn.functional.pad(v, (first, n - first - v.shape[0]))

    return per_frame


def skeleton_energy(st: ActorStack, delta, dtransl, opening, sl: slice, ctx, cfg: FitConfig, fps: float, after=None,
                    per_frame: bool = False):
    """Skeleton energy of all actors on timeline frames ``sl``, summed (a 0-d tensor; per frame ``(n,)``
    with ``per_frame``, see :func:`summer`, which needs no context): ``delta (A, n, 23, 3)``, ``dtransl
    (A, n, 3)``, ``opening (A, n, 4)``; ``ctx``: the context of up to two frames before ``sl`` (fixed,
    from the previous window) or None; ``after``: the same of up to two frames after it (a seam's
    window) or None. Returns (energy, rot): ``rot (A, n, 23, 3, 3)`` the driven bones' rotations (for
    the collision passes' full poses)."""
    if per_frame and (ctx is not None or after is not None):
        raise ValueError("per-frame skeleton energies are for the whole timeline: no context before or after")
    red = summer(delta.shape[1] if per_frame else None)
    rot = st.rotations(delta, sl)
    (joints, trk_heads, _), soles = st.skeleton(rot, st.transl0[:, sl] + dtransl)
    s_o = np.radians(cfg.sigma_orientation_deg)
    e = red((delta.pow(2).sum(-1) * st.seg_w[:, None, :]).sum(-1) * st.valid[:, sl]) / s_o**2
    if st.K:
        A, n = rot.shape[:2]
        idx = st.trk_seg[:, None, :, None].expand(A, n, st.K, 9)
        seg_frame = torch.gather(rot.reshape(A, n, -1, 9), 2, idx).reshape(A, n, st.K, 3, 3) @ st.trk_frame[:, None]
        site = trk_heads + (seg_frame @ st.trk_off[:, None, :, :, None])[..., 0]
        r = (site - st.trk_pos[:, sl]).pow(2).sum(-1) * st.trk_valid[:, sl]
        e = e + red(r) / cfg.sigma_tracker_m**2
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
        e = e + red(acc.pow(2), 1) / s_a**2
    e = e + red(torch.relu(-soles[..., 1]).pow(2)) / cfg.sigma_floor_m**2
    n_s = st.n_sole
    if cfg.sigma_contact_m > 0:
        y = torch.stack([soles[..., :n_s, 1], soles[..., n_s:, 1]], 2)  # (A, n, 2, n_sole)
        low = y.amin(-1)  # (A, n, 2); a soft minimum would sit below the lowest of a flat sole's many low points
        e = e + red(low.pow(2) * st.stance[:, sl].float()) / cfg.sigma_contact_m**2
    if soles_all.shape[1] >= 2:
        feet = torch.stack([soles_all[:, :, :n_s].mean(2), soles_all[:, :, n_s:].mean(2)], 2)  # (A, n', 2, 3)
        step = (feet[:, 1:] - feet[:, :-1])[..., 0::2].pow(2).sum(-1)  # x and z (0::2: a view, not a gather)
        both = (stance[:, 1:] & stance[:, :-1]).float()
        e = e + red(step * both, 1) / cfg.sigma_slide_m**2
    return opening_energy(opening, ctx, after, cfg, fps, e, red), rot


def opening_energy(opening, ctx, after, cfg: FitConfig, fps: float, base=0.0, red=None):
    """The hand openings' terms of :func:`skeleton_energy`, added to ``base`` (:func:`skeleton_energy`
    passes its bones' terms, so the sum keeps its order): the prior toward relaxed hands, the walls of
    :data:`OPENING_RANGE` and the openings' second difference over ``ctx``'s, ``opening (A, n, 4)``'s
    and ``after``'s frames (contexts as for :func:`skeleton_energy`; only their openings are read),
    reduced by ``red`` (:func:`summer`; None: summed).
    The hands' collision pass moves nothing else, so this is all of the skeleton energy that changes
    there."""
    o = torch.cat([x for x in (None if ctx is None else ctx[2], opening, None if after is None else after[2]) if x is not None], 1)
    red = red or summer(None)
    lo, hi = OPENING_RANGE
    e = base + red(opening.pow(2)) / cfg.sigma_hand_opening**2
    e = e + red(torch.relu(opening - hi).pow(2) + torch.relu(lo - opening).pow(2)) / 0.01**2
    if o.shape[1] >= 3:
        s_h = cfg.sigma_hand_opening_accel_s2 / fps**2
        e = e + red((o[:, 2:] - 2 * o[:, 1:-1] + o[:, :-2]).pow(2), 1) / s_h**2
    return e


def context_of(act: ActorTensors, delta, dtransl, opening, sl: slice) -> tuple:
    """One actor's context of fixed frames around the ones being fitted: (joints ``(m, 22, 3)``, sole
    vertices ``(m, 2 n_sole, 3)``, openings ``(m, 4)``) of timeline frames ``sl`` with the corrections
    ``delta``/``dtransl``/``opening`` (call it without gradient)."""
    rot = act.rotations(delta, sl)
    (joints, _, _), sole = act.skeleton(rot, act.transl0[sl] + dtransl)
    return joints, sole, opening


def stack_contexts(ctxs: list):
    """Per-actor contexts (all of one length, or all None) as one with the actors' axis first, for
    :func:`skeleton_energy`; None when they are None."""
    if ctxs[0] is None:
        return None
    return tuple(torch.stack([c[i] for c in ctxs]) for i in range(3))


def join_contexts(a, b, last: bool):
    """Two consecutive contexts of one actor (either None) as one, cut to its last two frames
    (``last``) or its first two; None when both are None."""
    parts = [x for x in (a, b) if x is not None]
    if not parts:
        return None
    cut = slice(-2, None) if last else slice(0, 2)
    return tuple(torch.cat([x[i] for x in parts], 0)[cut] for i in range(3))

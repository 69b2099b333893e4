"""Mounting of VIVE trackers on suit segments, and the suit world against the tracker world.

Model, for ``K`` trackers on one actor, tracker ``k`` strapped to suit segment ``k``, every sample
on one common timeline ``t``::

    R_tr,k(t) = Y(t) R_seg,k(t) M_k
    p_tr,k(t) = Y(t) p_seg,k(t) + d(t) + Y(t) R_seg,k(t) m_k  [+ Y(t) sum_a [dp_a]x R_a eps_a]

* ``R_seg``, ``p_seg``: the suit's segment orientation (segment -> suit world) and origin (suit
  world, m); ``R_tr``, ``p_tr``: the tracker's pose in the tracker world (drift-free reference);
* ``M_k``: tracker frame in the segment frame (rotation), ``m_k``: tracker origin in the segment
  frame (m) — the mount, constant;
* ``Y(t)``: rotation about world +Y by ``psi(t)`` (rad), the suit's heading in the tracker world (a
  constant offset plus a slow drift), piecewise linear on knots;
* ``d(t)``: translation (m, tracker world), the suit's position drift plus any constant offset
  between the worlds, piecewise linear on finer knots with a random-walk prior;
* optional (:class:`SuitChain`): ``eps_a``, the constant misalignment of each suit segment ``a`` on
  the chain from the root to tracker ``k``'s segment, moving it by ``[dp_a]x R_a eps_a`` (first
  order; ``dp_a`` the bone from ``a`` towards the tracker, ``R_a`` its measured orientation).

:func:`calibrate_mounts` estimates all of these; :class:`MountCalibration` carries them and maps
suit poses into the tracker world and tracker poses back onto their segments. The solve is split
by part: rotations and heading in :mod:`.mount_rotation`, offsets, drift and chain in
:mod:`.mount_translation`, the heading offset from the tracker sites in
:mod:`.mount_constellation`, the types in :mod:`.mount_types`. Design: ``docs/design/sync.md``.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.sync.knots import Knots, at_knots
from dualhuman_builder.sync.mount_constellation import HeadingProblem
from dualhuman_builder.sync.mount_rotation import (MOVED_DEG, flag_outliers, quat_matrices, rotation_residual,
                                                   rotation_rounds, yaw_matrices)  # fmt: skip
from dualhuman_builder.sync.mount_translation import TranslationDesign
from dualhuman_builder.sync import priors
from dualhuman_builder.sync.mount_types import CarriedMounts, MountCalibration, SuitChain

#: Least valid data (s) a calibration needs; fewer raise ValueError.
_MIN_DURATION_S = 2.0
#: Least inlier samples for a tracker to be calibrated (fewer: NaN entries, ``calibrated`` False).
_MIN_SAMPLES = 10
#: Position residuals above max(OUTLIER_FACTOR x median, this) are outliers (m).
_TRANS_FLOOR_M = 0.02
#: Prior std (m) of a mount offset without tracker sites: a weak ridge that keeps a segment that
#: hardly rotates solvable (its ``translation_std_m`` then comes out large).
_MOUNT_PRIOR_M = 1.0
#: Prior std per axis (m) of a mount offset around its site, when sites are given
#: (:data:`~dualhuman_builder.sync.priors.SITE_M`; ``docs/decisions/0011-heading-from-tracker-constellation.md``).
SITE_PRIOR_M = priors.SITE_M
#: Residuals count as one independent observation per this many seconds (they are correlated over
#: about that time): it sets the weight of data against priors and inflates the uncertainties.
_BLOCK_S = 1.0
#: Floor (m, per axis) of a carried mount offset's prior std: calibration takes state their offsets
#: more confidently than they are right (``benchmarks/bench_fit_accuracy.py --calibration``;
#: ``docs/decisions/0013-calibration-take.md``).
CARRIED_FLOOR_M = 0.004

__all__ = ["CARRIED_FLOOR_M", "MOVED_DEG", "SITE_PRIOR_M", "CarriedMounts", "MountCalibration", "SuitChain",
           "calibrate_mounts"]  # fmt: skip


def _mean_cov(v: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Covariance ``(D, D)`` of the mean of samples ``v (n, D)`` at times ``t (n,)``: the white
    estimate, inflated when ~1-s block means scatter more than white noise would."""
    n = v.shape[0]
    if n < 2:
        return np.full((v.shape[1], v.shape[1]), np.nan)
    white = np.atleast_2d(np.cov(v, rowvar=False)) / n
    blk = np.floor((t - t[0]) / _BLOCK_S).astype(np.int64)
    nb = int(blk.max()) + 1
    counts = np.bincount(blk, minlength=nb)
    ok = counts > 0
    if ok.sum() >= 8:
        means = np.stack([np.bincount(blk, v[:, d], nb)[ok] / counts[ok] for d in range(v.shape[1])], -1)
        cnt = counts[ok].astype(np.float64)
        dev = means - np.average(means, axis=0, weights=cnt)
        cov_blocks = (dev * cnt[:, None]).T @ dev / n / (ok.sum() - 1)
        tr_w, tr_b = np.trace(white), np.trace(cov_blocks)
        if tr_w > 0 and tr_b > tr_w:
            white = white * (tr_b / tr_w)
    return white



def _check_inputs(times_s, seg_rot, seg_pos, trk_rot, trk_pos, valid):
    t = np.asarray(times_s, dtype=np.float64)
    if t.ndim != 1:
        raise ValueError(f"times_s must be 1-D (T,), got shape {t.shape}")
    T = t.shape[0]
    arrays = {}
    for name, arr, last in (("seg_rot", seg_rot, 4), ("seg_pos", seg_pos, 3), ("trk_rot", trk_rot, 4),
                            ("trk_pos", trk_pos, 3)):  # fmt: skip
        a = np.asarray(arr, dtype=np.float64)
        if a.ndim != 3 or a.shape[0] != T or a.shape[2] != last:
            raise ValueError(f"{name} must have shape (T={T}, K, {last}), got {a.shape}")
        arrays[name] = a
    K = arrays["seg_rot"].shape[1]
    if K == 0:
        raise ValueError("need at least one tracker (K = 0)")
    for name, a in arrays.items():
        if a.shape[1] != K:
            raise ValueError(f"{name} has {a.shape[1]} trackers, seg_rot has {K}")
    v = np.asarray(valid)
    if v.dtype != bool or v.shape != (T, K):
        raise ValueError(f"valid must be a bool array of shape ({T}, {K}), got {v.dtype} {v.shape}")
    if not np.all(np.isfinite(t)):
        raise ValueError("times_s has non-finite values")
    if T >= 2 and np.any(np.diff(t) <= 0):
        raise ValueError("times_s must increase strictly")
    for name in ("seg_pos", "trk_pos"):
        if not np.all(np.isfinite(arrays[name][v])):
            raise ValueError(f"{name} has non-finite values at valid samples")
    return t, arrays["seg_rot"], arrays["seg_pos"], arrays["trk_rot"], arrays["trk_pos"], v


def calibrate_mounts(times_s, seg_rot, seg_pos, trk_rot, trk_pos, valid, knot_spacing_s: float = 1.0,
                     drift_knot_spacing_s: float = 0.1, drift_rate_m_per_sqrt_s: float = priors.ROOT_DRIFT_M_PER_SQRT_S,
                     rounds: int = 4, sites=None, site_prior_m: float = SITE_PRIOR_M,
                     chain: SuitChain | None = None, carried: CarriedMounts | None = None) -> MountCalibration:  # fmt: skip
    """Estimate tracker mounts, the suit's heading and its position drift (model in the module
    docstring).

    Inputs, ``T`` samples on one timeline, ``K`` trackers (tracker ``k`` on segment ``k``):
    ``times_s (T,)`` s, strictly increasing; ``seg_rot (T, K, 4)`` xyzw segment -> suit world and
    ``seg_pos (T, K, 3)`` segment origins (suit world, m); ``trk_rot (T, K, 4)`` xyzw and
    ``trk_pos (T, K, 3)`` m tracker poses in the tracker world; ``valid (T, K)`` bool (suit and
    tracker sample both usable). Values at invalid samples are ignored (may be NaN).

    Method: the heading starts from the best constant (grid search over the summed chordal fit);
    then ``rounds`` times (a) ``M_k`` = chordal mean of ``(Y R_seg)^-1 R_tr`` and (b) ``psi`` =
    piecewise-linear fit (knots every ``knot_spacing_s``) of the yaw of ``R_tr M_k^-1 R_seg^-1``,
    with rotation outliers rejected; then ``m_k`` and ``d`` (knots every ``drift_knot_spacing_s``,
    random-walk prior of ``drift_rate_m_per_sqrt_s`` per axis, the MAP for a drifting position) by
    sparse linear least squares with Huber reweighting, rejecting position outliers; the whole is
    repeated once if new outliers appeared. Samples at exactly the origin with ``valid`` True
    (trackers that lost tracking) are outliers from the start. A weak prior (``m ~ N(0, 1 m^2)``)
    keeps a segment that hardly rotates solvable, with a large ``translation_std_m``.

    ``sites (K, 3)`` (m, segment frame; optional): where each tracker is strapped on its segment
    (the capture protocol's site, e.g. :data:`~dualhuman_builder.rig.TRACKER_SITES`). Orientations
    alone cannot tell the heading from a yaw shared by all mounts while the segments do not turn
    (an actor standing still): then the tracker constellation decides. With sites, ``m_k ~ N(site_k, site_prior_m^2)``
    per axis, and a constant heading offset is searched (a 2-degree grid over +-20 degrees, then a
    parabola) minimising the negative log-likelihood of the orientation and position residuals
    plus that prior, with the mounts and drift re-solved at each offset; residuals are counted
    as one independent observation per ~1 s (they are correlated over that time), so a
    well-turning actor is decided by its data and a still one by its constellation. The offset's
    1-sigma (from the parabola's curvature) is ``heading_std_deg``, added in quadrature to every
    ``rotation_std_deg``.

    ``chain`` (:class:`SuitChain`, optional): the suit's segments from its root to each tracker's;
    each one's constant misalignment ``eps`` (prior ``N(0, chain.prior_deg^2)`` per axis) is solved
    with the mounts and the drift, so that a limb the suit places with misaligned orientations
    does not end up in the offsets (the ``chain_*`` fields of the result).

    ``carried`` (:class:`CarriedMounts`, optional): mounts solved on the studio day's calibration
    take. A carried tracker keeps its mounting rotation; the heading is fitted to the carried
    trackers' orientations alone (no constellation search: the carried rotations fix it, to
    ``heading_std_deg`` = their spread over sqrt(count)); its translation's prior is centred on the
    carried one with the calibration's uncertainty (per axis ``translation_std_m / sqrt(3)``, at
    least :data:`CARRIED_FLOOR_M`) instead of the site's; the chain's misalignment priors are
    centred on the calibration's. A carried tracker whose rotation residuals have a median above
    :data:`MOVED_DEG` was strapped again since: it is solved afresh and flagged in
    ``carry_rejected`` (one at a time, the worst first, since one moved tracker tilts the heading
    the others see). Trackers not carried are solved as without it, with the heading the carried
    ones give.

    Returns a :class:`MountCalibration`. A tracker with fewer than 10 usable samples gets NaN
    entries and ``calibrated[k] = False``. Raises ``ValueError`` on malformed input (shapes, NaN
    at valid samples, non-increasing times) or if fewer than 2 s of valid data remain.
    """
    t, q_seg, p_seg, q_trk, p_trk, valid = _check_inputs(times_s, seg_rot, seg_pos, trk_rot, trk_pos, valid)
    for name, val in (("knot_spacing_s", knot_spacing_s), ("drift_knot_spacing_s", drift_knot_spacing_s),
                      ("drift_rate_m_per_sqrt_s", drift_rate_m_per_sqrt_s)):  # fmt: skip
        if not (val > 0 and math.isfinite(val)):
            raise ValueError(f"{name} must be positive and finite, got {val}")
    T, K = valid.shape
    frames = np.flatnonzero(valid.any(axis=1))
    dt = float(np.median(np.diff(t))) if T >= 2 else 0.0
    duration = frames.size * dt
    if T < 2 or duration < _MIN_DURATION_S:
        raise ValueError(f"only {duration:.2f} s of valid data; need at least {_MIN_DURATION_S} s to calibrate mounts")

    Rs = quat_matrices("seg_rot", q_seg, valid)
    Rt = quat_matrices("trk_rot", q_trk, valid)
    origin = valid & np.all(p_trk == 0.0, axis=-1)
    use = valid & ~origin
    if use.sum() < _MIN_SAMPLES:
        raise ValueError("no tracker has usable samples (all invalid or at the origin)")

    hk = Knots(float(t[0]), float(t[-1]), knot_spacing_s)
    hj, hu = hk.locate(t)
    dk = Knots(float(t[0]), float(t[-1]), drift_knot_spacing_s)
    dj, du = dk.locate(t)

    obs_per_sample = min(1.0, dt / _BLOCK_S) if dt > 0 else 1.0  # ~one independent observation per second
    if sites is None:
        m0, m_prec = np.zeros((K, 3)), 1.0 / _MOUNT_PRIOR_M**2
    else:
        m0 = np.asarray(sites, dtype=np.float64)
        if m0.shape != (K, 3) or not np.all(np.isfinite(m0)):
            raise ValueError(f"sites must be finite with shape ({K}, 3), got {m0.shape}")
        if not (site_prior_m > 0 and math.isfinite(site_prior_m)):
            raise ValueError(f"site_prior_m must be positive and finite, got {site_prior_m}")
        m_prec = 1.0 / (site_prior_m**2 * obs_per_sample)
    fixed = np.zeros(K, bool)
    M_carried = np.broadcast_to(np.eye(3), (K, 3, 3)).copy()
    if carried is not None:
        carried.check(K)
        fixed = carried.carried.copy()
        M_carried[fixed] = Rotation.from_quat(carried.rotations[fixed]).as_matrix()
    offered = fixed.copy()
    rejected = np.zeros(K, bool)
    while True:  # once, or again after a carried tracker is found strapped again
        psi_knots, rot_out, M, moved = rotation_rounds(Rs, Rt, use, np.zeros_like(valid), hk, hj, hu, rounds, fixed,
                                                       M_carried)  # fmt: skip
        if moved is None:
            break
        fixed[moved] = False
        rejected[moved] = True
    m_prec = np.broadcast_to(np.asarray(m_prec, np.float64), (K,)).copy()
    m0 = np.broadcast_to(m0, (K, 3)).copy()
    if fixed.any():
        m0[fixed] = carried.translations[fixed]
        std = np.maximum(np.nan_to_num(carried.translation_std_m[fixed], nan=0.0) / math.sqrt(3.0), CARRIED_FLOOR_M)
        m_prec[fixed] = 1.0 / (std**2 * obs_per_sample)
    design = TranslationDesign(K, m0, m_prec, chain, valid.any(axis=1), obs_per_sample,
                               eps0=carried.chain if carried is not None and fixed.any() else None)  # fmt: skip
    trans_out = np.zeros_like(valid)
    m = np.zeros((K, 3))
    eps = np.zeros((len(design.segments), 3))
    d_knots = np.zeros((dk.n, 3))
    cov_m = np.full((K, 3, 3), np.nan)
    for outer in range(2):
        if outer:
            psi_knots, rot_out, M, _ = rotation_rounds(Rs, Rt, use, trans_out, hk, hj, hu, rounds, fixed, M_carried,
                                                       psi_knots, rot_out)  # fmt: skip
        psi = at_knots(psi_knots, hj, hu)
        G = yaw_matrices(psi)[:, None] @ Rs

        # translations: y = p_tr - Y p_seg = d(t) + G m_k
        Yt = yaw_matrices(psi)
        y = np.where(valid[..., None], p_trk - np.einsum("tij,tkj->tki", Yt, np.where(valid[..., None], p_seg, 0.0)),
                     0.0)  # fmt: skip
        sigma = np.full(K, 0.01)
        huber = np.ones((T, K))
        prev_trans = trans_out.copy()
        for _ in range(4):
            inl = use & ~rot_out & ~trans_out
            w = inl * huber / sigma[None] ** 2
            m, eps, d_knots, cov, e = design.solve(dk, dj, du, G, Yt, y, w, drift_rate_m_per_sqrt_s)
            cov_m = design.mount_covariances(cov)
            d_t = at_knots(d_knots, dj, du)
            en = np.linalg.norm(e, axis=-1)
            trans_out = flag_outliers(en, use & ~rot_out, _TRANS_FLOOR_M)
            inl = use & ~rot_out & ~trans_out
            for k in range(K):
                ek = e[inl[:, k], k]
                if ek.shape[0] >= _MIN_SAMPLES:
                    sigma[k] = max(1.4826 * float(np.median(np.abs(ek))), 1e-4)
                    c = 3.0 * float(np.median(en[inl[:, k], k]))
                    huber[:, k] = np.minimum(1.0, c / np.maximum(en[:, k], 1e-12))
        if np.array_equal(trans_out, prev_trans) or outer == 1:
            break

    inl = use & ~rot_out & ~trans_out
    heading_std = 0.0
    offset = 0.0
    if fixed.any():
        heading_std = math.sqrt(float(np.nanmean(carried.rotation_std_deg[fixed] ** 2)) / int(fixed.sum()))
    elif sites is not None:
        problem = HeadingProblem(Rs, Rt, p_seg, p_trk, valid, inl, huber / sigma[None] ** 2, dk, dj, du,
                                 drift_rate_m_per_sqrt_s, design, obs_per_sample)  # fmt: skip
        offset, heading_std = problem.search(psi)
        psi_knots = psi_knots + offset
        psi = psi + offset
        G, M, m, eps, d_knots, cov, e, en = problem.solve(psi)
        cov_m = design.mount_covariances(cov)
        d_t = at_knots(d_knots, dj, du)
    counts = inl.sum(axis=0)
    calibrated = counts >= _MIN_SAMPLES
    ang, rv = rotation_residual(np.swapaxes(G @ M[None], -1, -2) @ Rt)
    rot_rms = np.full(K, np.nan)
    rot_std = np.full(K, np.nan)
    tr_rms = np.full(K, np.nan)
    tr_std = np.full(K, np.nan)
    for k in np.flatnonzero(calibrated):
        sel = inl[:, k]
        rot_rms[k] = math.degrees(math.sqrt(float(np.mean(ang[sel, k] ** 2))))
        rot_std[k] = math.hypot(math.degrees(math.sqrt(max(float(np.trace(_mean_cov(rv[sel, k], t[sel]))), 0.0))),
                                heading_std)  # fmt: skip
        if fixed[k]:
            rot_std[k] = float(carried.rotation_std_deg[k])
        tr_rms[k] = math.sqrt(float(np.mean(en[sel, k] ** 2)))
        ek = e[sel, k]
        white = np.atleast_2d(np.cov(ek, rowvar=False)) / ek.shape[0]
        infl = float(np.trace(_mean_cov(ek, t[sel])) / np.trace(white)) if np.trace(white) > 0 else 1.0
        tr_std[k] = math.sqrt(max(float(np.trace(cov_m[k])), 0.0) * max(infl, 1.0))
    rotations = Rotation.from_matrix(M).as_quat()
    if fixed.any():
        rotations[fixed] = carried.rotations[fixed]  # as carried, to the bit
    translations = m.copy()
    rotations[~calibrated] = np.nan
    translations[~calibrated] = np.nan
    return MountCalibration(
        rotations=rotations, translations=translations, heading_rad=psi.copy(), drift=d_t.copy(),
        rotation_rms_deg=rot_rms, translation_rms_m=tr_rms, rotation_std_deg=rot_std, translation_std_m=tr_std,
        outliers=valid & ~inl, calibrated=calibrated, heading_knots_s=hk.t.copy(), heading_knots_rad=psi_knots.copy(),
        drift_knots_s=dk.t.copy(), drift_knots_m=d_knots.copy(),
        heading_offset_deg=np.asarray(math.degrees(offset)), heading_std_deg=np.asarray(heading_std),
        chain_segments=np.asarray(design.segments, np.int64), chain_misalignment_rad=eps.copy(),
        chain_std_deg=design.chain_std_deg(cov),
        common_offset_std_m=np.asarray(design.common_std_m(G, yaw_matrices(psi), cov, inl) / math.sqrt(obs_per_sample)),
        carried=fixed & calibrated, carry_rejected=rejected & offered,
    )  # fmt: skip


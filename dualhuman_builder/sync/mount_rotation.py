"""Mounting rotations and the suit's heading: the rotation half of :func:`~.mount.calibrate_mounts`.

Model (module :mod:`.mount`): ``R_tr,k(t) = Y(t) R_seg,k(t) M_k``, with ``Y(t)`` the rotation about
world +Y by the heading ``psi(t)`` (rad, piecewise linear on knots). Rotations are ``(..., 3, 3)``
matrices here, quaternions xyzw at the edges; ``T`` samples, ``K`` trackers.

:func:`rotation_rounds` alternates the closed-form chordal mean of each ``M_k`` with a weighted
fit of the heading knots to the per-sample yaw of ``R_tr M_k^-1 R_seg^-1``, rejecting rotation
outliers (:func:`flag_outliers`). With carried mounts (:class:`~.mount_types.CarriedMounts`) those
rotations stay fixed, the heading follows them alone, and a carried tracker whose residuals say it
was strapped again is reported (:data:`MOVED_DEG`).
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solveh_banded
from scipy.spatial.transform import Rotation

from dualhuman_builder.sync.knots import Knots, at_knots

#: Rotation residuals above max(:data:`OUTLIER_FACTOR` x median, this) are outliers (rad).
ROT_FLOOR_RAD = math.radians(2.0)
#: Residuals above this many times their tracker's median are outliers (rotations and positions).
OUTLIER_FACTOR = 6.0
#: A carried mount whose rotation residuals on a take have a median above this (deg) belongs to a
#: tracker strapped again since the calibration take; it is solved afresh. A tracker that stayed
#: put has residuals of about 1 deg (``docs/decisions/0013-calibration-take.md``).
MOVED_DEG = 3.0


def yaw_matrices(psi: np.ndarray) -> np.ndarray:
    """``Y(psi)``: rotations ``(..., 3, 3)`` about world +Y by ``psi (...)`` rad."""
    c, s = np.cos(psi), np.sin(psi)
    Y = np.zeros(psi.shape + (3, 3))
    Y[..., 0, 0] = c
    Y[..., 0, 2] = s
    Y[..., 1, 1] = 1.0
    Y[..., 2, 0] = -s
    Y[..., 2, 2] = c
    return Y


def project_so3(A: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Nearest rotations ``(..., 3, 3)`` to ``A`` (maximising ``tr(R^T A)``) and that maximum."""
    U, S, Vt = np.linalg.svd(A)
    det = np.linalg.det(U @ Vt)
    D = np.ones(A.shape[:-2] + (3,))
    D[..., 2] = np.sign(det)
    D[D == 0] = 1.0
    R = (U * D[..., None, :]) @ Vt
    return R, np.sum(S * D, axis=-1)


def rotation_residual(E: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Angle (rad) and rotation vector of rotation matrices ``E (..., 3, 3)`` (accurate near 0)."""
    v = 0.5 * np.stack([E[..., 2, 1] - E[..., 1, 2], E[..., 0, 2] - E[..., 2, 0], E[..., 1, 0] - E[..., 0, 1]], -1)
    sin = np.linalg.norm(v, axis=-1)
    cos = 0.5 * (np.trace(E, axis1=-2, axis2=-1) - 1.0)
    ang = np.arctan2(sin, cos)
    with np.errstate(invalid="ignore", divide="ignore"):
        scale = np.where(sin > 1e-12, ang / sin, 1.0)
    return ang, v * scale[..., None]


def quat_matrices(name: str, q: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``(T, K, 3, 3)`` rotation matrices of quaternions ``(T, K, 4)``; identity where not valid."""
    qv = q[valid]
    norm = np.linalg.norm(qv, axis=-1)
    if not np.all(np.isfinite(qv)) or np.any(norm < 1e-9):
        raise ValueError(f"{name} has non-finite or zero-norm quaternions at valid samples")
    out = np.broadcast_to(np.eye(3), q.shape[:-1] + (3, 3)).copy()
    out[valid] = Rotation.from_quat(qv).as_matrix()
    return out


def flag_outliers(residual: np.ndarray, pool: np.ndarray, floor: float) -> np.ndarray:
    """Per tracker: samples of ``pool (T, K)`` whose ``residual (T, K)`` exceeds
    max(:data:`OUTLIER_FACTOR` x its median over ``pool``, ``floor``)."""
    out = np.zeros_like(pool)
    for k in range(pool.shape[1]):
        r = residual[pool[:, k], k]
        if r.size == 0:
            continue
        thr = max(OUTLIER_FACTOR * float(np.median(r)), floor)
        out[:, k] = pool[:, k] & (residual[:, k] > thr)
    return out


def _init_heading(Rs: np.ndarray, Rt: np.ndarray, w: np.ndarray) -> float:
    """Constant heading maximising the summed chordal agreement with every tracker's best mount:
    ``sum_k max_M tr(M^T sum_t (Y R_seg)^T R_tr)``, on a 0.5-degree grid."""
    Cm = np.diag([1.0, 0.0, 1.0])
    Sm = np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    Em = np.diag([0.0, 1.0, 0.0])
    # Y(psi)^T = cos(psi) Cm + sin(psi) Sm + Em
    parts = [np.einsum("tk,tkji,jl,tklm->kim", w, Rs, P, Rt, optimize=True) for P in (Cm, Sm, Em)]
    psi = np.linspace(-math.pi, math.pi, 720, endpoint=False)
    A = (np.cos(psi)[:, None, None, None] * parts[0] + np.sin(psi)[:, None, None, None] * parts[1]
         + parts[2][None])  # fmt: skip
    _, score = project_so3(A)
    return float(psi[int(np.argmax(score.sum(axis=1)))])


def _fit_heading(knots: Knots, j, u, Q: np.ndarray, w: np.ndarray, psi_now: np.ndarray) -> np.ndarray:
    """Piecewise-linear heading (knot values, rad) from ``Q (T, K, 3, 3) ≈ Y(psi)`` per sample:
    each sample's best yaw ``atan2(Q02 - Q20, Q00 + Q22)``, unwrapped next to ``psi_now (T,)``,
    weighted least squares with a tiny second-difference regulariser."""
    a = Q[..., 0, 0] + Q[..., 2, 2]
    b = Q[..., 0, 2] - Q[..., 2, 0]
    yaw = np.arctan2(b, a)
    ww = w * 0.5 * np.hypot(a, b)
    target = psi_now[:, None] + (yaw - psi_now[:, None] + math.pi) % (2 * math.pi) - math.pi
    K = w.shape[1]
    jj, uu = np.repeat(j, K), np.repeat(u, K)
    diag, off1, rhs = knots.normal(jj, uu, ww.ravel(), target.ravel())
    n = knots.n
    off2 = np.zeros(max(n - 2, 0))
    lam = 1e-3 * max(float(diag.sum()) / n, 1e-12)
    if n >= 3:  # second differences: D2^T D2
        d2 = np.zeros(n)
        o1 = np.zeros(n - 1)
        for c, e in ((0, 1.0), (1, -2.0), (2, 1.0)):
            d2[c: n - 2 + c] += e * e
        o1[: n - 2] += -2.0
        o1[1: n - 1] += -2.0
        diag = diag + lam * d2
        off1 = off1 + lam * o1
        off2 = off2 + lam * 1.0
    diag = diag + 1e-9 * lam
    ab = np.zeros((3, n))
    ab[2] = diag
    ab[1, 1:] = off1
    if n >= 3:
        ab[0, 2:] = off2
    return solveh_banded(ab, rhs)


def rotation_rounds(Rs, Rt, use, trans_out, hk: Knots, hj, hu, rounds: int, fixed: np.ndarray, M_fixed,
                    psi_knots: np.ndarray | None = None, rot_out: np.ndarray | None = None):  # fmt: skip
    """The rotation part of :func:`~.mount.calibrate_mounts`: ``rounds`` times the mounts ``M (K, 3, 3)``
    by the closed form (the ``fixed (K,)`` ones kept at ``M_fixed``) and the heading knots fitted to
    the trackers' orientations (to the fixed ones' alone when there are any), rejecting rotation
    outliers among ``use & ~trans_out``. Starts from ``psi_knots`` (default: the best constant)
    and the rotation outliers ``rot_out`` (default: none).
    Returns ``(psi_knots, rot_out (T, K), M, moved)``: ``moved`` the fixed tracker whose median
    residual angle is the largest above :data:`MOVED_DEG`, or None."""
    K = use.shape[1]
    anchor = fixed if fixed.any() else np.ones(K, bool)
    if psi_knots is None:
        if fixed.any():
            Q = Rt @ np.swapaxes(M_fixed, -1, -2)[None] @ np.swapaxes(Rs, -1, -2)
            w = (use & fixed[None]).astype(np.float64)
            yaw0 = math.atan2(float(np.sum(w * (Q[..., 0, 2] - Q[..., 2, 0]))), float(np.sum(w * (Q[..., 0, 0] + Q[..., 2, 2]))))
        else:
            yaw0 = _init_heading(Rs, Rt, use.astype(np.float64))
        psi_knots = np.full(hk.n, yaw0)
    rot_out = np.zeros_like(use) if rot_out is None else rot_out
    inl = use & ~rot_out & ~trans_out
    for _ in range(max(1, int(rounds))):
        psi = at_knots(psi_knots, hj, hu)
        G = yaw_matrices(psi)[:, None] @ Rs  # Y R_seg (T, K, 3, 3)
        M, _ = project_so3(np.einsum("tk,tkji,tkjl->kil", inl.astype(np.float64), G, Rt, optimize=True))
        if fixed.any():
            M[fixed] = M_fixed[fixed]
        Q = Rt @ np.swapaxes(M, -1, -2)[None] @ np.swapaxes(Rs, -1, -2)
        psi_knots = _fit_heading(hk, hj, hu, Q, (inl & anchor[None]).astype(np.float64), psi)
        psi = at_knots(psi_knots, hj, hu)
        G = yaw_matrices(psi)[:, None] @ Rs
        ang, _ = rotation_residual(np.swapaxes(G @ M[None], -1, -2) @ Rt)
        rot_out = flag_outliers(ang, use & ~trans_out, ROT_FLOOR_RAD)
        inl = use & ~rot_out & ~trans_out
    M, _ = project_so3(np.einsum("tk,tkji,tkjl->kil", inl.astype(np.float64), G, Rt, optimize=True))
    moved = None
    if fixed.any():
        M[fixed] = M_fixed[fixed]
        ang, _ = rotation_residual(np.swapaxes(G @ M[None], -1, -2) @ Rt)
        med = np.array([float(np.median(ang[use[:, k], k])) if fixed[k] and use[:, k].any() else 0.0 for k in range(K)])
        if med.max() > math.radians(MOVED_DEG):
            moved = int(np.argmax(med))
    return psi_knots, rot_out, M, moved


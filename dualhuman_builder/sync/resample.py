"""Resampling irregular streams onto a common timeline (vectorised over channels).

Times are float64 seconds on the timeline. A frame is *valid* when samples on both sides of it are
valid and no further apart than ``max_gap_s``; invalid frames hold NaN.
"""

from __future__ import annotations

import numpy as np


def _brackets(t_src: np.ndarray, t_dst: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(i0, i1, a)`` ``(T,)``: the source samples around each target time and the fraction of
    the way from ``i0`` to ``i1`` (0 where they coincide)."""
    i1 = np.searchsorted(t_src, t_dst, side="left")
    i1 = np.clip(i1, 1, len(t_src) - 1)
    i0 = i1 - 1
    span = t_src[i1] - t_src[i0]
    a = np.where(span > 0, (t_dst - t_src[i0]) / np.where(span > 0, span, 1.0), 0.0)
    return i0, i1, a


def _inside(t_src, t_dst, i0, i1, valid, max_gap_s) -> np.ndarray:
    """``(T,)`` bool: target times within the source span, bracketed by valid samples no more
    than ``max_gap_s`` apart."""
    ok = (t_dst >= t_src[0] - 1e-9) & (t_dst <= t_src[-1] + 1e-9) & (t_src[i1] - t_src[i0] <= max_gap_s)
    if valid is not None:
        ok = ok & valid[i0] & valid[i1]
    return ok


def resample_linear(t_src: np.ndarray, values: np.ndarray, t_dst: np.ndarray, valid: np.ndarray | None = None,
                    max_gap_s: float = 0.05) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Linear interpolation of ``values (N, ...)`` sampled at increasing ``t_src (N,)`` onto
    ``t_dst (T,)``. Returns ``(out (T, ...), valid (T,))``; invalid frames are NaN."""
    t_src = np.asarray(t_src, dtype=np.float64)
    if len(t_src) < 2:
        return np.full((len(t_dst), *values.shape[1:]), np.nan), np.zeros(len(t_dst), bool)
    i0, i1, a = _brackets(t_src, t_dst)
    shape = (-1,) + (1,) * (values.ndim - 1)
    out = values[i0] * (1.0 - a).reshape(shape) + values[i1] * a.reshape(shape)
    ok = _inside(t_src, t_dst, i0, i1, valid, max_gap_s) & np.isfinite(out.reshape(len(t_dst), -1)).all(axis=1)
    out[~ok] = np.nan
    return out, ok


def resample_quat(t_src: np.ndarray, quats: np.ndarray, t_dst: np.ndarray, valid: np.ndarray | None = None,
                  max_gap_s: float = 0.05) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Normalised linear interpolation (nlerp, hemisphere-aligned) of unit quaternions
    ``(N, ..., 4)`` xyzw onto ``t_dst``; at the 100-250 Hz of our devices it differs from slerp
    by far less than the sensors' noise. Returns ``(out (T, ..., 4), valid (T,))``."""
    t_src = np.asarray(t_src, dtype=np.float64)
    if len(t_src) < 2:
        return np.full((len(t_dst), *quats.shape[1:]), np.nan), np.zeros(len(t_dst), bool)
    i0, i1, a = _brackets(t_src, t_dst)
    q0, q1 = quats[i0], quats[i1]
    sign = np.where((q0 * q1).sum(-1, keepdims=True) < 0, -1.0, 1.0)
    shape = (-1,) + (1,) * (quats.ndim - 1)
    q = q0 * (1.0 - a).reshape(shape) + q1 * sign * a.reshape(shape)
    q /= np.linalg.norm(q, axis=-1, keepdims=True)
    ok = _inside(t_src, t_dst, i0, i1, valid, max_gap_s) & np.isfinite(q.reshape(len(t_dst), -1)).all(axis=1)
    q[~ok] = np.nan
    return q, ok

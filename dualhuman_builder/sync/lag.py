"""Residual lag between two streams of one rigid body (a VIVE tracker and the suit segment it is
strapped to), from the cross-correlation of their angular (or linear) speeds.

The angular speed ``|w|`` of a rigid body does not depend on the frame a sensor is mounted in (a
constant mounting rotation ``M`` turns ``q_k^-1 q_{k+1}`` into ``M^-1 q_k^-1 q_{k+1} M``, the same
angle) nor on a constant rotation of the world, so two sensors on one segment see the same speed
up to noise, whatever their mounting and world frames; the linear speed serves segments that move
without turning. :func:`angular_speed` and :func:`linear_speed` turn poses into speeds,
:func:`estimate_lag` finds the shift that best aligns two speed signals, :func:`combine_lags`
merges the lags of several trackers sharing one clock, and :func:`with_carried_lag` joins a
take's lag with the one the studio day's calibration take measured
(``docs/decisions/0009-tracker-lag-by-speed.md``, ``docs/decisions/0013-calibration-take.md``).

Sign convention: ``lag_ns > 0`` means stream b's timestamps are **late**: ``s_a(t) ≈ s_b(t + lag)``,
so ``t_b - lag_ns`` puts b on a's time axis.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.fft import irfft, next_fast_len, rfft
from scipy.optimize import minimize_scalar

#: Fine grid step of the correlation, ns (1 kHz).
_GRID_NS = 1_000_000
#: Grid points farther than this from a sample on both sides (a hole in the data) are excluded, ns.
_MAX_GAP_NS = 50_000_000
#: Shortest overlap of two streams (s) a lag is estimated from.
_MIN_OVERLAP_S = 2.0
#: Lowest normalised cross-correlation accepted as a shared motion.
_MIN_PEAK = 0.5
#: Angular-speed standard deviation (rad/s) below which a stream counts as motionless.
_MIN_MOTION_RAD_S = 0.02
#: A take's own lag farther than this from its calibration take's (ns): the latency changed.
LAG_CHANGED_NS = 3_000_000.0
#: Sub-window length for the uncertainty, s, and the most windows used.
_WINDOW_S = 1.0
_MAX_WINDOWS = 10


@dataclass(frozen=True)
class LagEstimate:
    """Lag of stream b behind stream a: ``s_a(t) ≈ s_b(t + lag_ns)`` (subtract ``lag_ns`` from b's
    times to align). ``std_ns``: 1-sigma uncertainty (spread of the sub-window estimates /
    sqrt(n_windows)); ``peak``: normalised cross-correlation at the lag, in [-1, 1];
    ``n_windows``: sub-windows behind ``std_ns``; ``n_estimates``: estimates combined (1 unless
    from :func:`combine_lags`)."""

    lag_ns: float
    std_ns: float
    peak: float
    n_windows: int
    n_estimates: int = 1

    def as_dict(self) -> dict:
        """JSON-able fields, units in the key names."""
        return {"lag_ns": float(self.lag_ns), "std_ns": float(self.std_ns), "peak": float(self.peak),
                "n_windows": int(self.n_windows), "n_estimates": int(self.n_estimates)}  # fmt: skip


def _check_times(name: str, t) -> np.ndarray:
    """``t`` as a 1-D numeric array of times (ns), finite; ValueError naming ``name`` otherwise."""
    t = np.asarray(t)
    if t.ndim != 1:
        raise ValueError(f"{name} must be 1-D, got shape {t.shape}")
    if t.dtype.kind not in "iuf":
        raise ValueError(f"{name} must be numeric ns, got dtype {t.dtype}")
    if t.dtype.kind == "f" and not np.all(np.isfinite(t)):
        raise ValueError(f"{name} has non-finite values")
    return t


def angular_speed(times_ns, quats_xyzw, valid=None, smooth_s: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """Angular speed (rad/s) of a rotating body from consecutive orientations.

    ``times_ns (N,)`` int64 ns, strictly increasing; ``quats_xyzw (N, 4)`` body-to-world
    orientations (x, y, z, w; any norm > 0); ``valid (N,)`` bool or None (all valid).

    For each pair ``k, k+1`` of valid samples the body-frame angular velocity is
    ``w_k = log(q_k^-1 q_{k+1}) / dt`` (rotation vector over the interval), stamped at the
    interval's midpoint. With ``smooth_s > 0`` the vectors are smoothed by a Gaussian in time
    (standard deviation ``smooth_s`` seconds, zero phase: no lag; weights by interval length, so
    uneven sampling is fine) **before** taking the norm: differencing white orientation noise
    (0.5 deg at 240 Hz gives ~3 rad/s per pair) would otherwise swamp the motion, and the norm
    would rectify that noise into the signal. The default 0.04 s (-3 dB at 3.3 Hz) keeps the
    0.2-3 Hz band of body motion; use the same value for both streams of a pair. A
    constant mounting rotation only rotates the vectors, so the smoothed speed is still
    mount-independent. ``smooth_s=0`` gives the raw ``angle(q_k^-1 q_{k+1}) / dt``.

    Returns ``(t_ns, speed)``: float64 ``(M,)`` midpoint times (ns) and speeds (rad/s), ``M <= N-1``
    (pairs touching an invalid sample are dropped).
    """
    def check(q, v):
        qv = q[v]
        if not np.all(np.isfinite(qv)) or np.any(np.linalg.norm(qv, axis=1) < 1e-9):
            raise ValueError("quats_xyzw has non-finite or zero-norm quaternions at valid samples")

    return _speed(times_ns, quats_xyzw, "quats_xyzw", 4, valid, smooth_s, "an angular speed", check, _relative_rotvec)


def linear_speed(times_ns, positions, valid=None, smooth_s: float = 0.04) -> tuple[np.ndarray, np.ndarray]:
    """Speed (m/s) of a moving point from consecutive positions, for the lag of a tracker whose
    segment translates but hardly turns (its angular speed carries no signal).

    ``times_ns (N,)`` strictly increasing; ``positions (N, 3)`` m in any fixed world frame (the
    speed does not depend on it); ``valid (N,)`` bool or None. Velocities of consecutive valid
    pairs, stamped at the interval midpoints, smoothed by a zero-phase Gaussian of ``smooth_s``
    seconds before the norm (as :func:`angular_speed`). A tracker and the origin of its segment
    differ by the lever arm's ``w x m`` (a few cm/s), not by a delay. Returns ``(t_ns, speed)``.
    """
    def check(p, v):
        if not np.all(np.isfinite(p[v])):
            raise ValueError("positions has non-finite values at valid samples")

    return _speed(times_ns, positions, "positions", 3, valid, smooth_s, "a speed", check, lambda p0, p1: p1 - p0)


def _speed(times_ns, values, name: str, width: int, valid, smooth_s: float, what: str, check, step):
    """Shared body of :func:`angular_speed` and :func:`linear_speed`: validate ``values (N, width)``
    against ``times_ns`` and ``valid`` (``check(values, valid)`` for the kind's own test), then
    ``step(x_k, x_k+1)`` per consecutive valid pair over its interval, stamped at the midpoint,
    Gaussian-smoothed (``smooth_s``) before the norm. Returns ``(t_ns, speed)``."""
    t = _check_times("times_ns", times_ns)
    x = np.asarray(values, dtype=np.float64)
    n = t.shape[0]
    if x.shape != (n, width):
        raise ValueError(f"{name} must have shape ({n}, {width}) to match times_ns, got {x.shape}")
    v = np.ones(n, dtype=bool) if valid is None else np.asarray(valid)
    if v.shape != (n,) or v.dtype != bool:
        raise ValueError(f"valid must be a bool array of shape ({n},), got {v.dtype} {v.shape}")
    if not (smooth_s >= 0 and math.isfinite(smooth_s)):
        raise ValueError(f"smooth_s must be finite and >= 0, got {smooth_s}")
    if n < 2:
        raise ValueError(f"need at least 2 samples for {what}, got {n}")
    if np.any(np.diff(t) <= 0):
        raise ValueError("times_ns must increase strictly")
    check(x, v)
    k = np.flatnonzero(v[:-1] & v[1:])
    if t.dtype.kind == "f":
        dt_ns = t[k + 1].astype(np.float64) - t[k]
    else:  # integer nanoseconds: exact differences before float64
        dt_ns = (t[k + 1] - t[k]).astype(np.float64)
    mid = t[k].astype(np.float64) + 0.5 * dt_ns
    if k.size == 0:
        return mid, np.zeros(0)
    rate = step(x[k], x[k + 1]) / (dt_ns * 1e-9)[:, None]
    if smooth_s > 0:
        rate = _gauss_smooth(mid, rate, dt_ns, smooth_s * 1e9)
    return mid, np.linalg.norm(rate, axis=1)


def _relative_rotvec(q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
    """Rotation vectors ``(M, 3)`` of ``q0^-1 q1`` (body frame of ``q0``) for xyzw quaternions."""
    q0 = q0 / np.linalg.norm(q0, axis=1, keepdims=True)
    q1 = q1 / np.linalg.norm(q1, axis=1, keepdims=True)
    v0, w0 = -q0[:, :3], q0[:, 3:]  # conjugate of q0
    v1, w1 = q1[:, :3], q1[:, 3:]
    v = w0 * v1 + w1 * v0 + np.cross(v0, v1)
    w = w0[:, 0] * w1[:, 0] - np.sum(v0 * v1, axis=1)
    sign = np.where(w < 0, -1.0, 1.0)  # shortest rotation
    v, w = v * sign[:, None], w * sign
    sin_half = np.linalg.norm(v, axis=1)
    angle = 2.0 * np.arctan2(sin_half, w)
    scale = np.where(sin_half > 1e-12, angle / np.maximum(sin_half, 1e-300), 2.0)
    return v * scale[:, None]


def _gauss_smooth(t_ns: np.ndarray, values: np.ndarray, weights: np.ndarray, sigma_ns: float) -> np.ndarray:
    """Gaussian-weighted average (std ``sigma_ns``) of ``values (M, D)`` at times ``t_ns (M,)``,
    each sample also weighted by ``weights`` (its interval length); truncated at 4 sigma."""
    m = t_ns.shape[0]
    lo = np.searchsorted(t_ns, t_ns - 4.0 * sigma_ns, side="left")
    hi = np.searchsorted(t_ns, t_ns + 4.0 * sigma_ns, side="right")
    reach = int(max(np.max(np.arange(m) - lo), np.max(hi - 1 - np.arange(m)), 0))
    num = np.zeros_like(values)
    den = np.zeros(m)
    for off in range(-reach, reach + 1):
        i0, i1 = max(0, -off), min(m, m - off)
        if i1 <= i0:
            continue
        d = (t_ns[i0 + off: i1 + off] - t_ns[i0:i1]) / sigma_ns
        g = np.exp(-0.5 * d * d) * weights[i0 + off: i1 + off]
        g[np.abs(d) > 4.0] = 0.0
        num[i0:i1] += g[:, None] * values[i0 + off: i1 + off]
        den[i0:i1] += g
    return num / den[:, None]


def _grid_values(t: np.ndarray, s: np.ndarray, g: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of ``s(t)`` at ``g`` (float ns) and a mask of points not inside a gap
    longer than :data:`_MAX_GAP_NS` nor outside ``[t[0], t[-1]]``."""
    idx = np.searchsorted(t, g, side="right")
    inside = (idx > 0) & (idx < t.shape[0])
    ic = np.clip(idx, 1, t.shape[0] - 1)
    ok = inside & (t[ic] - t[ic - 1] <= _MAX_GAP_NS)
    ok |= g == t[-1]
    return np.interp(g, t, s), ok


def _ncc_lags(a: np.ndarray, ma: np.ndarray, b: np.ndarray, mb: np.ndarray, max_shift: int) -> np.ndarray:
    """Masked normalised cross-correlation ``corr(a[i], b[i + L])`` for ``L = -max_shift..max_shift``."""
    fa, fb = ma.astype(np.float64), mb.astype(np.float64)
    A, B = a * fa, b * fb
    size = next_fast_len(a.shape[0] + b.shape[0] + 2 * max_shift)
    spec_a = {name: np.conj(rfft(u, size)) for name, u in (("1", fa), ("a", A), ("aa", A * a))}
    spec_b = {name: rfft(u, size) for name, u in (("1", fb), ("b", B), ("bb", B * b))}

    def xc(ka, kb):  # sum_i u[i] w[i + L] for L = -max_shift..max_shift
        full = irfft(spec_a[ka] * spec_b[kb], size)
        return np.concatenate([full[size - max_shift:], full[: max_shift + 1]])

    n = xc("1", "1")
    sa, sb = xc("a", "1"), xc("1", "b")
    saa, sbb = xc("aa", "1"), xc("1", "bb")
    sab = xc("a", "b")
    with np.errstate(invalid="ignore", divide="ignore"):
        cov = sab - sa * sb / n
        va = saa - sa * sa / n
        vb = sbb - sb * sb / n
        r = cov / np.sqrt(va * vb)
    r[(n < 10) | ~np.isfinite(r)] = -np.inf
    return r


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    """Normalised cross-correlation of equal-length ``a`` and ``b`` at zero shift (-1 when either is constant)."""
    a = a - a.mean()
    b = b - b.mean()
    den = math.sqrt(float(a @ a) * float(b @ b))
    return float(a @ b) / den if den > 0 else -1.0


def estimate_lag(t_a_ns, s_a, t_b_ns, s_b, max_lag_s: float = 0.1, min_motion: float = _MIN_MOTION_RAD_S) -> LagEstimate:
    """Lag of stream b behind stream a from their angular (or linear) speeds.

    ``t_a_ns (Na,)``, ``t_b_ns (Nb,)``: strictly increasing sample times, ns (float or int, as
    :func:`angular_speed` returns them); ``s_a``, ``s_b``: speeds (rad/s) at those times. The rates
    may differ (240 vs 250 Hz). Both are linearly interpolated on a 1 kHz grid over their overlap
    (grid points inside a hole > 50 ms in either stream are excluded), the masked normalised
    cross-correlation is searched over integer-ms shifts within ``±max_lag_s``, and the peak is
    refined to sub-sample precision by maximising the correlation with b re-interpolated at
    continuously shifted times (bounded Brent search, 1 us tolerance). ``std_ns`` comes from
    refining the lag in 1-s sub-windows (at most 10): their spread / sqrt(count).

    Returns a :class:`LagEstimate` with ``s_a(t) ≈ s_b(t + lag_ns)``: b's timestamps are late by
    ``lag_ns`` (subtract it from b's times to align).

    Raises ``ValueError`` if the overlap is shorter than 2 s, a stream hardly moves (speed std
    below ``min_motion``, rad/s or m/s: "not enough motion to estimate the lag"), the best correlation is below 0.5, or the peak lies at the edge
    of ``±max_lag_s``.
    """
    ta, tb = _check_times("t_a_ns", t_a_ns), _check_times("t_b_ns", t_b_ns)
    sa, sb = np.asarray(s_a, dtype=np.float64), np.asarray(s_b, dtype=np.float64)
    if sa.shape != ta.shape or sb.shape != tb.shape:
        raise ValueError(f"speeds must match their times: s_a {sa.shape} vs t_a {ta.shape}, "
                         f"s_b {sb.shape} vs t_b {tb.shape}")  # fmt: skip
    if not (np.all(np.isfinite(sa)) and np.all(np.isfinite(sb))):
        raise ValueError("s_a and s_b must be finite")
    if not (max_lag_s > 0 and math.isfinite(max_lag_s)):
        raise ValueError(f"max_lag_s must be positive, got {max_lag_s}")
    if ta.shape[0] < 2 or tb.shape[0] < 2:
        raise ValueError(f"need at least 2 samples per stream, got {ta.shape[0]} and {tb.shape[0]}")
    if ta.dtype.kind in "iu" and tb.dtype.kind in "iu":  # shift to a common origin before float64
        origin = min(int(ta[0]), int(tb[0]))
        ta, tb = (ta - origin).astype(np.float64), (tb - origin).astype(np.float64)
    else:
        origin = float(min(ta[0], tb[0]))
        ta, tb = ta.astype(np.float64) - origin, tb.astype(np.float64) - origin
    if np.any(np.diff(ta) <= 0) or np.any(np.diff(tb) <= 0):
        raise ValueError("t_a_ns and t_b_ns must increase strictly")
    lo, hi = max(ta[0], tb[0]), min(ta[-1], tb[-1])
    overlap_s = (hi - lo) * 1e-9
    if overlap_s < _MIN_OVERLAP_S:
        raise ValueError(f"the streams overlap for {max(overlap_s, 0.0):.3f} s; need at least {_MIN_OVERLAP_S} s")
    g = lo + _GRID_NS * np.arange(int(np.floor((hi - lo) / _GRID_NS)) + 1)
    A, ma = _grid_values(ta, sa, g)
    B, mb = _grid_values(tb, sb, g)
    std_a = float(np.std(A[ma])) if ma.any() else 0.0
    std_b = float(np.std(B[mb])) if mb.any() else 0.0
    if min(std_a, std_b) < min_motion:
        raise ValueError(f"not enough motion to estimate the lag (speed std a={std_a:.4f}, "
                         f"b={std_b:.4f}; need >= {min_motion})")  # fmt: skip
    max_shift = max(1, round(max_lag_s * 1e9 / _GRID_NS))
    max_shift = min(max_shift, g.shape[0] // 4)
    r = _ncc_lags(A, ma, B, mb, max_shift)
    best = int(np.argmax(r))
    peak0 = float(r[best])
    if not peak0 >= _MIN_PEAK:
        raise ValueError(f"correlation peak {peak0:.3f} is below {_MIN_PEAK}: the streams do not share their "
                         "motion (wrong pairing, or too much noise)")  # fmt: skip
    shift0 = best - max_shift
    if abs(shift0) == max_shift:
        raise ValueError(f"the correlation peaks at the edge of the search range ({shift0 * _GRID_NS * 1e-9:+.3f} s); "
                         "widen max_lag_s")  # fmt: skip

    # refine: b re-interpolated at continuously shifted times; fixed mask over the bracket
    span = 2 * _GRID_NS
    mask = ma.copy()
    for edge in (-span, 0, span):
        mask &= _grid_values(tb, sb, g + shift0 * _GRID_NS + edge)[1]
    idx = np.flatnonzero(mask)

    def refine(sel: np.ndarray) -> tuple[float, float]:
        a_sel, g_sel = A[sel], g[sel]

        def cost(tau_ns):
            return -_ncc(a_sel, np.interp(g_sel + tau_ns, tb, sb))

        c = shift0 * _GRID_NS
        res = minimize_scalar(cost, bounds=(c - span, c + span), method="bounded", options={"xatol": 1e3})
        return float(res.x), -float(res.fun)

    lag, peak = refine(idx)
    K = int(min(_MAX_WINDOWS, np.floor(overlap_s / _WINDOW_S)))
    lags = []
    if K >= 2:
        for part in np.array_split(idx, K):
            if part.size < 100 or np.std(A[part]) < _MIN_MOTION_RAD_S or np.std(B[part]) < _MIN_MOTION_RAD_S:
                continue
            lw, pw = refine(part)
            if pw >= _MIN_PEAK:
                lags.append(lw)
    std = float(np.std(lags, ddof=1) / math.sqrt(len(lags))) if len(lags) >= 2 else math.nan
    return LagEstimate(lag_ns=lag, std_ns=std, peak=peak, n_windows=len(lags))


def combine_lags(estimates, floor_ns: float = 100_000.0, max_dev_ns: float = 5_000_000.0) -> LagEstimate:
    """One lag from several estimates that should agree (trackers on one clock against their
    segments), each :class:`LagEstimate` with the same sign convention.

    Estimates farther from the median lag than ``min(3 * sqrt(std_i^2 + floor_ns^2), max_dev_ns)``
    are dropped (``floor_ns``, default 0.1 ms, keeps over-confident sub-window spreads from
    dropping consistent estimates; ``max_dev_ns`` default 5 ms); the rest are averaged with
    weights ``1 / (std_i^2 + floor_ns^2)``. ``std_ns`` of the result is ``1/sqrt(sum w)``,
    inflated by the Birge ratio (sqrt of chi^2 per degree of freedom) when that exceeds 1;
    ``peak`` is the weighted mean peak, ``n_windows`` the summed windows, ``n_estimates`` the
    number kept. Estimates with a NaN ``std_ns`` count with ``std = max_dev_ns``.
    Raises ``ValueError`` for no estimates or a non-finite lag, ``TypeError`` for other objects.
    """
    est = list(estimates)
    if not est:
        raise ValueError("combine_lags needs at least one LagEstimate")
    for e in est:
        if not isinstance(e, LagEstimate):
            raise TypeError(f"combine_lags takes LagEstimate objects, got {type(e).__name__}")
        if not math.isfinite(e.lag_ns):
            raise ValueError(f"lag_ns must be finite, got {e.lag_ns}")
    lag = np.array([e.lag_ns for e in est])
    std = np.array([e.std_ns if math.isfinite(e.std_ns) else max_dev_ns for e in est])
    sig = np.sqrt(std**2 + floor_ns**2)
    med = float(np.median(lag))
    keep = np.abs(lag - med) <= np.minimum(3.0 * sig, max_dev_ns)
    if not keep.any():
        keep = np.abs(lag - med) == np.min(np.abs(lag - med))
    w = 1.0 / sig[keep] ** 2
    mean = float(np.sum(w * lag[keep]) / np.sum(w))
    out_std = 1.0 / math.sqrt(float(np.sum(w)))
    dof = int(keep.sum()) - 1
    if dof > 0:
        chi2 = float(np.sum(w * (lag[keep] - mean) ** 2))
        out_std *= max(1.0, math.sqrt(chi2 / dof))
    peaks = np.array([e.peak for e in est])[keep]
    return LagEstimate(lag_ns=mean, std_ns=out_std, peak=float(np.sum(w * peaks) / np.sum(w)),
                       n_windows=int(sum(e.n_windows for e, k in zip(est, keep) if k)),
                       n_estimates=int(keep.sum()))  # fmt: skip


def with_carried_lag(own: LagEstimate | None, carried: LagEstimate, changed_ns: float = LAG_CHANGED_NS,
                     floor_ns: float = 100_000.0) -> tuple[LagEstimate, bool]:
    """One source's lag from this take's own estimate ``own`` (None: no tracker of the source moved
    enough) and ``carried``, the lag the studio day's calibration take measured for the same source.

    The lag is the difference of two transport latencies (the trackers' and the suits'), a property
    of the devices and the network that holds for the day, so a calibration take (long, every
    segment turning) measures it better than a short take whose actors hardly move
    (``docs/decisions/0013-calibration-take.md``). The two are averaged with weights
    ``1 / (std^2 + floor_ns^2)`` (a non-finite ``std_ns`` counts as ``changed_ns``); the result's
    ``std_ns`` is ``1 / sqrt(sum w)``. When ``own`` lies farther than ``changed_ns`` (default 3 ms)
    from ``carried``, the latency changed since the calibration (a restarted or re-configured
    source): ``own`` is returned alone with ``changed=True``. The result's ``peak`` is ``own``'s.
    Returns ``(estimate, changed)``."""
    if not math.isfinite(carried.lag_ns):
        raise ValueError(f"the carried lag must be finite, got {carried.lag_ns}")
    if own is None:
        return carried, False
    if abs(own.lag_ns - carried.lag_ns) > changed_ns:
        return own, True
    ests = (own, carried)
    std = np.array([e.std_ns if math.isfinite(e.std_ns) else changed_ns for e in ests])
    w = 1.0 / (std**2 + floor_ns**2)
    lag = float(np.sum(w * np.array([e.lag_ns for e in ests])) / np.sum(w))
    return LagEstimate(lag_ns=lag, std_ns=1.0 / math.sqrt(float(np.sum(w))), peak=own.peak,
                       n_windows=own.n_windows + carried.n_windows,
                       n_estimates=own.n_estimates + carried.n_estimates), False  # fmt: skip

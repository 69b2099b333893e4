"""Device clock -> host clock: a robust line through a stream's (device, host) timestamp pairs.

Every sample carries ``device_time_ns`` (the device's own clock) and ``host_time_ns`` (the host's
monotonic clock at receipt), both int64 ns. Between them::

    host = intercept + slope * (device - ref) + delay,      delay >= 0

``slope`` is host seconds per device second (1 + drift), and ``delay`` the transport latency plus
queueing/network jitter. Delays are one-sided — a packet can arrive late, never early — so the
line that maps device time to "host time at the minimum delay" is the **lower envelope** of the
points, not their mean: :func:`fit_clock` solves the linear programme

    maximise  sum_i (intercept + slope * x_i)   subject to   intercept + slope * x_i <= y_i,

(minimise the summed delay above the line) whose solution is the edge of the points' lower convex
hull above the mean device time (Moon, Skelly & Towsley, "Estimation and removal of clock skew
from network delay measurements", IEEE INFOCOM 1999). Delayed packets and bursts lie above the
line and cannot move it; points below it (impossible for true delays: stamp glitches) are found
against a Theil-Sen line through per-block minima and removed before the final hull.

The host time that :meth:`ClockFit.to_host` returns is therefore the receive time of a packet with
the smallest delay seen (constant latency included): the host clock reading at the moment of
sampling is ``to_host(device) - latency`` for a latency known from elsewhere.

Quantised stamps: MVN's time code counts whole milliseconds (floor). The envelope of floor-
quantised stamps maps the stamp itself, i.e. the start of its quantum; a sample was taken on
average half a quantum later, so ``to_host(device_ns + quantum / 2)`` is the unbiased host time of
such a sample (the quantum cannot be told from the data: a device stepping 4 ms exactly looks
the same).

Decision record: ``docs/decisions/0008-clock-lower-envelope.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.stats import theilslopes

#: Fewest stamp pairs a clock is fitted from.
_MIN_SAMPLES = 10
#: Bootstrap replicates for the uncertainties (fixed seed: the fit is deterministic).
_BOOTSTRAP = 64
#: Target number of samples per block (negative-outlier check and bootstrap).
_BLOCK_SAMPLES = 50
#: Bounds on the number of blocks.
_MAX_BLOCKS = 200
_MIN_BLOCKS = 5


@dataclass(frozen=True)
class ClockFit:
    """``host_ns ≈ intercept_ns + slope * (device_ns - ref_device_ns)`` at the minimum delay.

    ``slope``: host seconds per device second. ``intercept_ns``: host ns (float) at device time
    ``ref_device_ns`` (int, the first device stamp given). ``n``: samples given; ``n_used``:
    samples on or near the lower envelope (delay above the line within the jitter's robust range:
    neither rejected as below the envelope nor part of a delayed burst). ``residual_std_ns``:
    standard deviation of those samples' delays above the line (the jitter). ``intercept_std_ns``
    and ``slope_std``: 1-sigma uncertainties (block bootstrap of the envelope fit).
    """

    slope: float
    intercept_ns: float
    ref_device_ns: int
    n: int
    n_used: int
    residual_std_ns: float
    intercept_std_ns: float
    slope_std: float

    @property
    def drift_ppm(self) -> float:
        """``(slope - 1) * 1e6``: positive when the device clock runs slow against the host."""
        return (self.slope - 1.0) * 1e6

    def to_host(self, device_ns) -> np.ndarray:
        """Host time (float64 ns, minimum-delay receive time) of device stamps ``device_ns`` (any
        shape, int or float ns on this device's clock)."""
        return self.intercept_ns + self.slope * _minus(device_ns, self.ref_device_ns)

    def to_device(self, host_ns) -> np.ndarray:
        """Inverse of :meth:`to_host`: device time (float64 ns) whose minimum-delay receive time is
        ``host_ns``."""
        return self.ref_device_ns + (np.asarray(host_ns, dtype=np.float64) - self.intercept_ns) / self.slope

    def device_to(self, other: ClockFit, device_ns) -> np.ndarray:
        """This device's stamps ``device_ns`` expressed on ``other``'s device clock (float64 ns),
        through the host: ``other.to_device(self.to_host(device_ns))``. Both fits must come from
        streams received by the same host clock."""
        return other.to_device(self.to_host(device_ns))

    def as_dict(self) -> dict:
        """JSON-able summary with units in the key names (inverse: :meth:`from_dict`)."""
        return {
            "slope_host_s_per_device_s": float(self.slope),
            "intercept_host_ns": float(self.intercept_ns),
            "ref_device_ns": int(self.ref_device_ns),
            "n_samples": int(self.n),
            "n_used": int(self.n_used),
            "residual_std_ns": float(self.residual_std_ns),
            "intercept_std_ns": float(self.intercept_std_ns),
            "slope_std": float(self.slope_std),
            "drift_ppm": float(self.drift_ppm),
        }

    @classmethod
    def from_dict(cls, d: dict) -> ClockFit:
        """A fit from :meth:`as_dict`'s output."""
        return cls(slope=float(d["slope_host_s_per_device_s"]), intercept_ns=float(d["intercept_host_ns"]),
                   ref_device_ns=int(d["ref_device_ns"]), n=int(d["n_samples"]), n_used=int(d["n_used"]),
                   residual_std_ns=float(d["residual_std_ns"]), intercept_std_ns=float(d["intercept_std_ns"]),
                   slope_std=float(d["slope_std"]))  # fmt: skip


def relative_clock(fit_a: ClockFit, fit_b: ClockFit) -> tuple[float, float]:
    """Map stream b's device clock onto stream a's through their common host clock.

    Returns ``(slope, intercept_ns)`` with
    ``device_a ≈ intercept_ns + slope * (device_b - fit_b.ref_device_ns)``: ``slope`` is a-device
    seconds per b-device second and ``intercept_ns`` a's device time (float ns) at b's reference
    stamp. Equivalent to ``fit_b.device_to(fit_a, device_b)``. Each stream's latency stays in it:
    if a and b have different minimum delays, the difference appears in ``intercept_ns``.
    """
    slope = fit_b.slope / fit_a.slope
    intercept = float(fit_a.to_device(fit_b.intercept_ns))
    return float(slope), intercept


def _minus(values, ref: int) -> np.ndarray:
    """``values - ref`` as float64 without losing integer precision of large int64 stamps."""
    arr = np.asarray(values)
    if arr.dtype.kind in "iu":
        return (arr.astype(np.int64) - np.int64(ref)).astype(np.float64)
    return arr.astype(np.float64) - float(ref)


def _lower_hull(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Indices of the lower convex hull of points sorted by strictly increasing ``x``."""
    hull: list[int] = []
    for i in range(x.shape[0]):
        while len(hull) >= 2:
            o, a = hull[-2], hull[-1]
            # drop a when it lies on or above the segment o -> i
            if (x[a] - x[o]) * (y[i] - y[o]) - (y[a] - y[o]) * (x[i] - x[o]) <= 0:
                hull.pop()
            else:
                break
        hull.append(i)
    return np.asarray(hull, dtype=np.int64)


def _hull_candidates(x: np.ndarray, y: np.ndarray, slope0: float) -> np.ndarray:
    """Mask of points that can be lower-hull vertices (``x`` sorted, strictly increasing): after
    shearing by ``slope0`` (which keeps the hull), a vertex must be a running minimum from the left
    or from the right; any other point lies above the chord between those two minima."""
    z = y - slope0 * x
    left = np.minimum.accumulate(z)
    right = np.minimum.accumulate(z[::-1])[::-1]
    return (z <= left) | (z <= right)


def _envelope(x: np.ndarray, y: np.ndarray, x_mean: float, slope0: float = 0.0) -> tuple[float, float]:
    """``(a, b)`` of the line ``a + b x`` below every point with the largest value at ``x_mean``
    (the LP solution); ``x`` sorted and strictly increasing, at least two points."""
    idx = np.flatnonzero(_hull_candidates(x, y, slope0))
    hx, hy = x[idx], y[idx] - slope0 * x[idx]
    h = _lower_hull(hx, hy)
    hx, hy = hx[h], hy[h]
    if hx.shape[0] == 1:  # cannot happen with two distinct x, kept for safety
        return float(hy[0]), slope0
    j = int(np.clip(np.searchsorted(hx, x_mean, side="right") - 1, 0, hx.shape[0] - 2))
    b = (hy[j + 1] - hy[j]) / (hx[j + 1] - hx[j])
    a = hy[j] - b * hx[j]
    return float(a), float(b + slope0)


def _unique_min(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique ``x`` with the smallest ``y`` of each (duplicate device stamps)."""
    order = np.lexsort((y, x))
    xs, ys = x[order], y[order]
    first = np.ones(xs.shape[0], dtype=bool)
    first[1:] = xs[1:] != xs[:-1]
    return xs[first], ys[first]


def _blocks(n: int) -> np.ndarray:
    """Start indices of equal-count blocks over ``n`` sorted samples."""
    nb = int(np.clip(n // _BLOCK_SAMPLES, _MIN_BLOCKS, _MAX_BLOCKS))
    nb = min(nb, max(n // 2, 1))
    return np.unique(np.linspace(0, n, nb + 1)[:-1].astype(np.int64))


def fit_clock(device_ns, host_ns) -> ClockFit:
    """Fit ``host ≈ intercept + slope * (device - device_ns[0])`` to the lower envelope of the
    stamp pairs of one stream (see the module docstring).

    ``device_ns``, ``host_ns``: ``(N,)`` int64 (or float) ns, one pair per received sample, in any
    order; duplicate device stamps are allowed. Delayed packets (any positive extra delay, bursts
    included) are ignored by construction; stamps lying below the envelope (glitches) are
    rejected. Runs in O(N log N).

    Raises ``ValueError`` for fewer than 10 samples, arrays of different lengths or not 1-D,
    non-finite values, or device time that does not increase over the stream.
    """
    dev = np.asarray(device_ns)
    host = np.asarray(host_ns)
    if dev.ndim != 1 or host.ndim != 1:
        raise ValueError(f"device_ns and host_ns must be 1-D, got shapes {dev.shape} and {host.shape}")
    if dev.shape != host.shape:
        raise ValueError(f"device_ns and host_ns differ in length: {dev.shape[0]} vs {host.shape[0]}")
    n = dev.shape[0]
    if n < _MIN_SAMPLES:
        raise ValueError(f"need at least {_MIN_SAMPLES} samples to fit a clock, got {n}")
    for name, arr in (("device_ns", dev), ("host_ns", host)):
        if arr.dtype.kind not in "iuf":
            raise ValueError(f"{name} must be numeric, got dtype {arr.dtype}")
        if arr.dtype.kind == "f" and not np.all(np.isfinite(arr)):
            raise ValueError(f"{name} has {int(np.sum(~np.isfinite(arr)))} non-finite values")
    ref = int(dev[0])
    host_ref = int(host[0])
    x_all = _minus(dev, ref)
    y_all = _minus(host, host_ref)
    steps = np.diff(x_all)
    if x_all[-1] <= 0 or np.count_nonzero(steps < 0) > 0.25 * steps.shape[0]:
        raise ValueError(
            "device time does not increase over the stream (last stamp "
            f"{'<=' if x_all[-1] <= 0 else '>'} first, {int(np.count_nonzero(steps < 0))} of {steps.shape[0]} "
            "steps go backwards)"
        )

    order = np.lexsort((y_all, x_all))
    x, y = x_all[order], y_all[order]
    keep = np.ones(n, dtype=bool)
    x_mean = float(x.mean())
    for _ in range(4):
        ux, uy = _unique_min(x[keep], y[keep])
        if ux.shape[0] < 2:
            raise ValueError("device time does not increase over the stream (fewer than 2 distinct stamps left)")
        a, b = _envelope(ux, uy, x_mean, 1.0)
        r = y - (a + b * x)
        # negative outliers: samples far below a robust line through per-block minima
        starts = _blocks(n)
        rk = np.where(keep, r, np.inf)
        bmin = np.minimum.reduceat(rk, starts)
        ok = np.isfinite(bmin)
        if ok.sum() < 3:
            break
        # x of each block's minimum: index of the minimum within its block
        bidx = np.empty(starts.shape[0], dtype=np.int64)
        ends = np.append(starts[1:], n)
        for j, (s0, s1) in enumerate(zip(starts, ends)):
            bidx[j] = s0 + int(np.argmin(rk[s0:s1]))
        bx, by = x[bidx][ok], bmin[ok]
        ts_slope, ts_icpt, _, _ = theilslopes(by, bx)
        e = by - (ts_icpt + ts_slope * bx)
        sigma = 1.4826 * float(np.median(np.abs(e - np.median(e))))
        thr = max(10.0 * sigma, 1000.0)  # at least 1 us below
        low = keep & (r - (ts_icpt + ts_slope * x) < -thr)
        if not low.any():
            break
        keep &= ~low

    r = y - (a + b * x)
    rk = r[keep]
    med = float(np.median(rk))
    mad = 1.4826 * float(np.median(np.abs(rk - med)))
    upper = med + max(5.0 * mad, 1000.0)
    used = keep & (r <= upper)
    n_used = int(used.sum())
    residual_std = float(np.std(r[used])) if n_used > 1 else 0.0

    # uncertainties: bootstrap over blocks of the kept samples
    ux, uy = _unique_min(x[keep], y[keep])
    cand = np.flatnonzero(_block_candidates(ux, uy, b))
    starts = _blocks(ux.shape[0])
    block_of = np.searchsorted(starts, cand, side="right") - 1
    rng = np.random.default_rng(0)
    a_bs, b_bs = [], []
    nb = starts.shape[0]
    for _ in range(_BOOTSTRAP):
        chosen = np.zeros(nb, dtype=bool)
        chosen[rng.integers(0, nb, nb)] = True
        sel = cand[chosen[block_of]]
        if np.unique(ux[sel]).shape[0] < 2:
            continue
        ab, bb = _envelope(ux[sel], uy[sel], x_mean, b)
        a_bs.append(ab)
        b_bs.append(bb)
    a_std = float(np.std(a_bs, ddof=1)) if len(a_bs) > 2 else math.nan
    b_std = float(np.std(b_bs, ddof=1)) if len(b_bs) > 2 else math.nan
    if b <= 0:
        raise ValueError(f"device time does not increase with host time (fitted slope {b:.3g})")
    return ClockFit(slope=float(b), intercept_ns=float(host_ref) + a, ref_device_ns=ref, n=int(n), n_used=n_used,
                    residual_std_ns=residual_std, intercept_std_ns=a_std, slope_std=b_std)  # fmt: skip


def _block_candidates(x: np.ndarray, y: np.ndarray, slope0: float) -> np.ndarray:
    """Mask of points that can be lower-hull vertices of any union of blocks (running minima from
    the left or the right within their own block); ``x`` sorted, strictly increasing."""
    n = x.shape[0]
    starts = _blocks(n)
    sizes = np.diff(np.append(starts, n))
    m = int(sizes.max())
    z = y - slope0 * x
    pad = np.full((starts.shape[0], m), np.inf)
    row = np.repeat(np.arange(starts.shape[0]), sizes)
    col = np.arange(n) - np.repeat(starts, sizes)
    pad[row, col] = z
    left = np.minimum.accumulate(pad, axis=1)
    right = np.minimum.accumulate(pad[:, ::-1], axis=1)[:, ::-1]
    mask = (pad <= left) | (pad <= right)
    return mask[row, col]

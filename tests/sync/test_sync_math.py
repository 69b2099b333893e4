"""Sync-stage math: device->host clock fits, tracker/segment lag by angular-speed correlation, and
tracker mount / heading / drift calibration. Synthetic streams with known truth; timestamps come
from the simulator's :class:`DeviceClock`."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as R

from dualhuman_builder.rig import TRACKER_SITES
from dualhuman_builder.sim.kinematics import DeviceClock
from dualhuman_builder.sync.clock import ClockFit, fit_clock, relative_clock
from dualhuman_builder.sync.lag import (
    LagEstimate,
    angular_speed,
    combine_lags,
    estimate_lag,
    linear_speed,
    with_carried_lag,
)
from dualhuman_builder.sync.mount import MOVED_DEG, CarriedMounts, MountCalibration, SuitChain, calibrate_mounts

TRACKER_CLOCK = DeviceClock(offset_s=0.25, drift_ppm=30.0, latency_s=0.004, jitter_s=0.001)
#: host seconds per device second for TRACKER_CLOCK, as ppm
TRUE_DRIFT_PPM = (1.0 / (1.0 + 30e-6) - 1.0) * 1e6


# ------------------------------------------------------------------------------------ clock
def clock_stream(seed, clock=TRACKER_CLOCK, rate=250.0, duration=20.0, quantise=False, bursts=False):
    """(device_ns given to the fit, host_ns, unquantised device_ns, true scene ns)."""
    rng = np.random.default_rng(seed)
    dev, true = clock.sample_times(0, int(duration * 1e9), rate)
    host = clock.host_time_ns(true, rng)
    if bursts:  # 5 % of samples in bursts of 25 whose queue delay decays from up to 100 ms
        n = true.shape[0]
        extra = np.zeros(n)
        for s in rng.choice(n - 25, int(0.05 * n / 25), replace=False):
            extra[s:s + 25] = np.maximum(extra[s:s + 25], rng.uniform(0.01, 0.1) * np.linspace(1, 0.04, 25) * 1e9)
        host = np.maximum.accumulate(host + extra.astype(np.int64))
    given = dev[0] + (dev - dev[0]) // 1_000_000 * 1_000_000 if quantise else dev
    return given, host, dev, true


@pytest.mark.parametrize("case, rate, quantise, bursts", [
    ("plain", 250.0, False, False),
    ("1 ms floor-quantised stamps (MVN time code)", 240.0, True, False),
    ("5 % delayed bursts up to 100 ms", 250.0, False, True),
    ("quantised and bursts", 240.0, True, True),
])  # fmt: skip
def test_fit_clock_recovers_min_delay_line_and_drift(case, rate, quantise, bursts):
    given, host, dev, true = clock_stream(11, rate=rate, quantise=quantise, bursts=bursts)
    fit = fit_clock(given, host)
    err_ms = (fit.to_host(dev) - (true + TRACKER_CLOCK.latency_s * 1e9)) / 1e6
    assert np.abs(err_ms).max() < 0.2, case
    assert abs(fit.drift_ppm - TRUE_DRIFT_PPM) < 2.0, case
    assert fit.ref_device_ns == int(given[0]) and fit.n == given.shape[0]
    assert 0.9 * fit.n < fit.n_used <= fit.n
    # jitter is exponential with mean 1 ms: its std is ~1 ms; uncertainties are small and positive
    assert 0.6e6 < fit.residual_std_ns < 1.4e6
    assert 0 < fit.intercept_std_ns < 0.1e6 and 0 < fit.slope_std < 2e-6
    if bursts:
        assert fit.n_used < 0.97 * fit.n  # the delayed bursts are not "near the envelope"
    if quantise:  # floor-quantised: the sample sits on average ~half a quantum after its stamp
        stamped = fit.to_host(given) - (true + TRACKER_CLOCK.latency_s * 1e9)
        centred = fit.to_host(given + 500_000) - (true + TRACKER_CLOCK.latency_s * 1e9)
        assert -0.6e6 < stamped.mean() < -0.3e6 and abs(centred.mean()) < 0.1e6  # 240 Hz: mean floor loss 0.42 ms


def test_fit_clock_ten_minutes_with_duplicates_and_arrival_order():
    given, host, dev, true = clock_stream(3, duration=600.0, bursts=True)
    n0 = given.shape[0]
    assert n0 >= 150_000
    rng = np.random.default_rng(0)
    dup = rng.choice(given.shape[0], 1500, replace=False)  # re-sent packets: same stamp, later arrival
    given = np.concatenate([given, given[dup]])
    host = np.concatenate([host, host[dup] + rng.integers(1_000_000, 20_000_000, dup.shape[0])])
    order = np.argsort(host, kind="stable")  # the order of arrival
    fit = fit_clock(given[order], host[order])
    err = fit.to_host(dev) - (true + TRACKER_CLOCK.latency_s * 1e9)
    assert np.abs(err).max() < 0.05e6
    assert abs(fit.drift_ppm - TRUE_DRIFT_PPM) < 0.2
    assert fit.n == n0 + 1500


def test_fit_clock_rejects_stamps_below_the_envelope():
    given, host, dev, true = clock_stream(5)
    given, host = given.copy(), host.copy()
    given[2000] += 30_000_000  # a device-stamp glitch: 30 ms ahead puts the point far below the line
    host[4000] -= 5_000_000  # a host stamp 5 ms early
    fit = fit_clock(given, host)
    err = fit.to_host(dev) - (true + TRACKER_CLOCK.latency_s * 1e9)
    assert np.abs(err).max() < 0.05e6
    assert fit.n_used <= fit.n - 2
    # without the rejection the line would run through the glitch, ~1 ms low on average
    assert abs(fit.drift_ppm - TRUE_DRIFT_PPM) < 1.0


def test_clock_fit_round_trips_and_relative_clock():
    suit_clock = DeviceClock(offset_s=0.0, drift_ppm=-12.0, latency_s=0.002, jitter_s=0.0005)
    g_s, h_s, _, _ = clock_stream(1, clock=suit_clock, rate=240.0)
    g_t, h_t, dev_t, true_t = clock_stream(2)
    fs, ft = fit_clock(g_s, h_s), fit_clock(g_t, h_t)
    # inverse
    x = np.array([dev_t[0], dev_t[100], dev_t[-1]])
    assert np.allclose(ft.to_device(ft.to_host(x)), x, atol=1e-3)
    # tracker stamps on the suit clock: scene time + the latency difference, on the suit clock
    expected = suit_clock.device_time_ns(true_t + (TRACKER_CLOCK.latency_s - suit_clock.latency_s) * 1e9)
    on_suit = ft.device_to(fs, dev_t)
    assert np.abs(on_suit - expected).max() < 0.2e6
    slope, intercept = relative_clock(fs, ft)
    assert np.allclose(intercept + slope * (dev_t - ft.ref_device_ns), on_suit, atol=1.0)
    assert abs((slope - 1) * 1e6 - (-12.0 - 30.0)) < 3.0
    # JSON round trip with units in the keys
    d = json.loads(json.dumps(ft.as_dict()))
    assert {"slope_host_s_per_device_s", "intercept_host_ns", "drift_ppm", "residual_std_ns"} <= set(d)
    assert ClockFit.from_dict(d) == ft


@pytest.mark.parametrize("device, host, message", [
    (np.arange(5) * 4_000_000, np.arange(5) * 4_000_000, "at least 10 samples"),
    (np.arange(20) * 4_000_000, np.arange(19) * 4_000_000, "differ in length"),
    (np.r_[np.nan, np.arange(1.0, 20.0)] * 4e6, np.arange(20) * 4_000_000, "device_ns has 1 non-finite"),
    (np.arange(20) * 4_000_000, np.r_[np.arange(19.0), np.inf] * 4e6, "host_ns has 1 non-finite"),
    (np.arange(20)[::-1] * 4_000_000, np.arange(20) * 4_000_000, "device time does not increase"),
    (np.zeros(20, dtype=np.int64), np.arange(20) * 4_000_000, "device time does not increase"),
    (np.arange(20 * 2).reshape(20, 2), np.arange(40).reshape(20, 2), "must be 1-D"),
])  # fmt: skip
def test_fit_clock_errors(device, host, message):
    with pytest.raises(ValueError, match=message):
        fit_clock(device, host)


# ------------------------------------------------------------------------------------ lag
def smooth_motion(seed):
    """A smooth random 3-D rotation: rotation vector = sums of sines at 0.2-3 Hz (~1-4 rad/s)."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.2, 3.0, (3, 4))
    ph = rng.uniform(0.0, 2 * np.pi, (3, 4))
    amp = rng.uniform(0.05, 0.2, (3, 4)) / f

    def rot(t):
        return R.from_rotvec(np.einsum("ij,tij->ti", amp, np.sin(2 * np.pi * f * t[:, None, None] + ph)))

    return rot, rng


def noisy(rot, deg, rng):
    return rot * R.from_rotvec(rng.normal(0.0, math.radians(deg) / math.sqrt(3.0), (len(rot), 3)))


def lag_pair(seed, lag_s=0.0023, duration=20.0):
    rot, rng = smooth_motion(seed)
    ta = np.arange(0.0, duration, 1 / 240)
    tb = np.arange(0.0017, duration, 1 / 250)  # b's stamps; its samples were taken lag_s earlier
    mount = R.from_rotvec([0.4, -1.1, 0.7])
    qa = noisy(rot(ta), 0.5, rng).as_quat()
    qb = noisy(rot(tb - lag_s) * mount, 0.3, rng).as_quat()
    return (ta * 1e9).astype(np.int64), qa, (tb * 1e9).astype(np.int64), qb


def test_angular_speed_of_constant_rotation_is_mount_and_world_independent():
    t = np.arange(500) * 4_000_000  # 250 Hz
    rate = 2.5  # rad/s about a tilted axis
    axis = np.array([1.0, 2.0, -0.5]) / np.linalg.norm([1.0, 2.0, -0.5])
    body = R.from_rotvec(np.outer(t * 1e-9 * rate, axis))
    world, mount = R.from_rotvec([0.3, 0.2, 0.1]), R.from_rotvec([1.0, -0.4, 0.8])
    q_a = body.as_quat()
    q_b = (world * body * mount).as_quat()
    for smooth in (0.0, 0.04):
        ts_a, s_a = angular_speed(t, q_a, smooth_s=smooth)
        _, s_b = angular_speed(t, q_b, smooth_s=smooth)
        assert s_a.shape == (499,) and np.allclose(s_a, rate, atol=1e-9) and np.allclose(s_b, rate, atol=1e-9)
        assert np.array_equal(ts_a, t[:-1] + 2_000_000.0) and ts_a.dtype == np.float64
    valid = np.ones(500, dtype=bool)
    valid[[10, 300]] = False
    ts, s = angular_speed(t, q_a, valid)
    assert s.shape == (495,) and 10 * 4e6 - 2e6 not in ts and 10 * 4e6 + 2e6 not in ts


def test_angular_speed_errors():
    t = np.arange(10) * 4_000_000
    q = R.random(10, random_state=0).as_quat()
    with pytest.raises(ValueError, match="quats_xyzw must have shape"):
        angular_speed(t, q[:9])
    with pytest.raises(ValueError, match="increase strictly"):
        angular_speed(t[::-1], q)
    with pytest.raises(ValueError, match="zero-norm"):
        angular_speed(t, np.r_[q[:9], [[0.0, 0, 0, 0]]])
    with pytest.raises(ValueError, match="valid must be a bool"):
        angular_speed(t, q, np.ones(10))


def test_estimate_lag_recovers_2_3_ms_between_240_and_250_hz_streams():
    ta, qa, tb, qb = lag_pair(4)
    a, b = angular_speed(ta, qa), angular_speed(tb, qb)
    est = estimate_lag(*a, *b)
    assert abs(est.lag_ns - 2.3e6) < 0.3e6
    assert 0 < est.std_ns < 0.3e6 and est.n_windows == 10 and est.peak > 0.95
    # the sign flips with the roles
    back = estimate_lag(*b, *a)
    assert abs(back.lag_ns + est.lag_ns) < 0.1e6
    # a 0.3-s hole in b and a different max_lag change little
    keep = (tb < 7e9) | (tb > 7.3e9)
    b_gap = angular_speed(tb[keep], qb[keep])
    est_gap = estimate_lag(*a, *b_gap, max_lag_s=0.05)
    assert abs(est_gap.lag_ns - 2.3e6) < 0.3e6


def test_estimate_lag_large_lag_and_edge_of_search():
    ta, qa, tb, qb = lag_pair(6, lag_s=0.040)
    a, b = angular_speed(ta, qa), angular_speed(tb, qb)
    assert abs(estimate_lag(*a, *b).lag_ns - 40e6) < 0.3e6
    with pytest.raises(ValueError, match="edge of the search range"):
        estimate_lag(*a, *b, max_lag_s=0.02)


def test_estimate_lag_errors():
    ta, qa, tb, qb = lag_pair(1)
    a, b = angular_speed(ta, qa), angular_speed(tb, qb)
    short = tb < 1.5e9
    with pytest.raises(ValueError, match="overlap for 1.4"):
        estimate_lag(*a, *angular_speed(tb[short], qb[short]))
    still = np.tile(R.from_rotvec([0.1, 0.2, 0.3]).as_quat(), (tb.shape[0], 1))
    with pytest.raises(ValueError, match="not enough motion to estimate the lag"):
        estimate_lag(*a, *angular_speed(tb, still))
    other_t, other_q, _, _ = lag_pair(2)
    with pytest.raises(ValueError, match="below 0.5"):
        estimate_lag(*a, *angular_speed(other_t, other_q))
    with pytest.raises(ValueError, match="speeds must match"):
        estimate_lag(a[0], a[1][:-1], *b)


def test_linear_speed_and_a_lag_from_positions():
    """A point moving on a smooth path: linear_speed gives |dp/dt| (any world rotation), skips
    invalid samples, and two streams of it, one stamped 7 ms late, give that lag."""
    t = np.arange(0.0, 8.0, 1 / 240)
    path = lambda x: np.stack([0.3 * np.sin(1.3 * x), 0.1 * np.sin(0.7 * x + 1), 0.2 * np.cos(2.1 * x)], -1)  # noqa: E731
    true_speed = lambda x: np.linalg.norm(np.stack([0.39 * np.cos(1.3 * x), 0.07 * np.cos(0.7 * x + 1),  # noqa: E731
                                                    -0.42 * np.sin(2.1 * x)], -1), axis=1)  # fmt: skip
    ns = np.round(t * 1e9).astype(np.int64)
    mid, sp = linear_speed(ns, R.from_rotvec([0, 1.0, 0]).apply(path(t)), smooth_s=0.0)
    assert np.abs(sp - true_speed(mid * 1e-9)).max() < 1e-3
    valid = np.ones(t.shape, bool)
    valid[100] = False
    mid_v, _ = linear_speed(ns, path(t), valid)
    assert mid_v.shape[0] == t.shape[0] - 3  # the two pairs touching sample 100 are dropped
    tb = np.arange(0.0, 8.0, 1 / 250)
    late = np.round((tb + 0.007) * 1e9).astype(np.int64)
    est = estimate_lag(*linear_speed(ns, path(t)), *linear_speed(late, path(tb)), min_motion=0.02)
    assert abs(est.lag_ns - 7e6) < 0.3e6
    with pytest.raises(ValueError, match=r"positions must have shape \(1920, 3\)"):
        linear_speed(ns, path(t)[:, :2])
    bad = path(t)
    bad[5] = np.nan
    with pytest.raises(ValueError, match="positions has non-finite values at valid samples"):
        linear_speed(ns, bad)
    with pytest.raises(ValueError, match="need at least 2 samples for a speed"):
        linear_speed(ns[:1], path(t)[:1])


def test_combine_lags_drops_the_odd_one_and_weights_by_variance():
    good = [LagEstimate(2.3e6, 0.05e6, 0.99, 10), LagEstimate(2.4e6, 0.1e6, 0.98, 10),
            LagEstimate(2.25e6, 0.05e6, 0.99, 10)]  # fmt: skip
    bad = LagEstimate(9.0e6, 0.05e6, 0.9, 10)
    out = combine_lags(good + [bad])
    assert out.n_estimates == 3 and out.n_windows == 30
    w = np.array([1 / (0.05**2 + 0.1**2), 1 / (0.1**2 + 0.1**2), 1 / (0.05**2 + 0.1**2)])
    expected = float(np.sum(w * np.array([2.3, 2.4, 2.25])) / w.sum()) * 1e6
    assert out.lag_ns == pytest.approx(expected)
    assert 0 < out.std_ns < 0.1e6
    # real estimates from three tracker pairs sharing one lag
    ests = []
    for seed in (7, 8, 9):
        ta, qa, tb, qb = lag_pair(seed)
        ests.append(estimate_lag(*angular_speed(ta, qa), *angular_speed(tb, qb)))
    comb = combine_lags(ests)
    assert abs(comb.lag_ns - 2.3e6) < 0.2e6 and comb.n_estimates == 3
    with pytest.raises(ValueError, match="at least one"):
        combine_lags([])



def test_a_calibration_takes_lag_is_averaged_in_unless_the_latency_changed():
    """The studio day's calibration take measured the trackers' lag behind the suits to 0.15 ms; a
    short take's own 0.75 +/- 0.35 ms is averaged with it by inverse variance; a take without a lag of its own takes the carried one; one 4 ms
    away means the latency changed, and keeps its own."""
    carried = LagEstimate(2.1e6, 0.15e6, 0.99, 40, 24)
    own = LagEstimate(0.75e6, 0.35e6, 0.97, 20, 16)
    out, changed = with_carried_lag(own, carried)
    w = np.array([1 / (0.35**2 + 0.1**2), 1 / (0.15**2 + 0.1**2)])
    assert not changed
    assert out.lag_ns == pytest.approx(float(np.sum(w * np.array([0.75, 2.1])) / w.sum()) * 1e6)
    assert 1.8e6 < out.lag_ns < 2.1e6 and out.std_ns == pytest.approx(1e6 / np.sqrt(w.sum()))
    assert out.std_ns < math.hypot(carried.std_ns, 0.1e6) and out.peak == own.peak and out.n_estimates == 40
    assert with_carried_lag(None, carried) == (carried, False)
    moved = LagEstimate(6.1e6, 0.3e6, 0.99, 20, 16)
    assert with_carried_lag(moved, carried) == (moved, True)
    # an estimate without a spread weighs as little as a change of latency
    vague, _ = with_carried_lag(LagEstimate(1.0e6, math.nan, 0.9, 1), carried)
    assert abs(vague.lag_ns - 2.1e6) < 0.01e6
    with pytest.raises(ValueError, match="carried lag must be finite"):
        with_carried_lag(own, LagEstimate(math.nan, 0.1e6, 0.9, 1))


# ------------------------------------------------------------------------------------ mounts
def mount_scene(seed, duration=20.0, rate=40.0, K=6):
    """Synthetic suit segments and trackers following the calibration model exactly."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    T = t.shape[0]
    f = rng.uniform(0.1, 1.0, (K, 3, 3))
    ph = rng.uniform(0.0, 2 * np.pi, (K, 3, 3))
    amp = rng.uniform(0.3, 1.0, (K, 3, 3))
    rv = np.einsum("kij,tkij->tki", amp, np.sin(2 * np.pi * f * t[:, None, None, None] + ph))
    base = np.tile(R.random(K, random_state=seed).as_quat(), (T, 1))
    seg_rot = (R.from_rotvec(rv.reshape(-1, 3)) * R.from_quat(base)).as_quat().reshape(T, K, 4)
    fp, pp = rng.uniform(0.05, 0.5, (K, 3)), rng.uniform(0.0, 2 * np.pi, (K, 3))
    seg_pos = np.array([0.0, 1.0, 0.0]) + 0.5 * np.sin(2 * np.pi * fp * t[:, None, None] + pp)
    mounts = R.from_rotvec(rng.normal(0.0, math.radians(10.0) / math.sqrt(3.0), (K, 3)))
    offsets = rng.normal(0.0, 0.1 / math.sqrt(3.0), (K, 3))
    psi = math.radians(30.0) + math.radians(1.0) / 60.0 * t
    steps = rng.standard_normal((T, 3)) * 0.05 / math.sqrt(60.0) * math.sqrt(1.0 / rate)
    drift = np.array([1.0, 0.0, -2.0]) + np.cumsum(steps, axis=0)
    Y = R.from_rotvec(np.repeat(psi, K)[:, None] * np.array([0.0, 1.0, 0.0]))
    Rseg = R.from_quat(seg_rot.reshape(-1, 4))
    Rtr = Y * Rseg * R.from_quat(np.tile(mounts.as_quat(), (T, 1)))
    Rtr = Rtr * R.from_rotvec(rng.normal(0.0, math.radians(0.3) / math.sqrt(3.0), (T * K, 3)))
    ptr = (Y.apply(seg_pos.reshape(-1, 3)) + np.repeat(drift, K, axis=0) + (Y * Rseg).apply(np.tile(offsets, (T, 1)))
           + rng.normal(0.0, 0.001, (T * K, 3)))  # fmt: skip
    trk_rot, trk_pos = Rtr.as_quat().reshape(T, K, 4), ptr.reshape(T, K, 3)
    valid = rng.random((T, K)) > 0.05
    trk_rot[~valid] = np.nan
    trk_pos[~valid] = np.nan
    jumps = rng.choice(T * K, 8, replace=False)  # tracking lost, reported at the origin as valid
    trk_pos.reshape(-1, 3)[jumps] = 0.0
    trk_rot.reshape(-1, 4)[jumps] = [0.0, 0.0, 0.0, 1.0]
    valid.reshape(-1)[jumps] = True
    truth = {"mounts": mounts, "offsets": offsets, "psi": psi, "drift": drift, "jumps": jumps}
    return (t, seg_rot, seg_pos, trk_rot, trk_pos, valid), truth


@pytest.mark.parametrize("rate", [30.0, 60.0])
def test_calibrate_mounts_recovers_mounts_heading_and_drift(rate):
    inputs, truth = mount_scene(1, rate=rate)
    cal = calibrate_mounts(*inputs)
    assert isinstance(cal, MountCalibration) and cal.calibrated.all()
    rot_err = np.degrees((R.from_quat(cal.rotations).inv() * truth["mounts"]).magnitude())
    assert rot_err.max() < 0.3
    assert np.linalg.norm(cal.translations - truth["offsets"], axis=1).max() < 0.002
    assert np.degrees(np.sqrt(np.mean((cal.heading_rad - truth["psi"]) ** 2))) < 0.1
    assert np.sqrt(np.mean(np.sum((cal.drift - truth["drift"]) ** 2, axis=1))) < 0.002
    # origin jumps rejected, little else
    assert cal.outliers.reshape(-1)[truth["jumps"]].all() and cal.outliers.sum() < 20
    # residuals match the noise (0.3 deg; 1 mm per axis plus drift between knots); stds are honest
    assert np.allclose(cal.rotation_rms_deg, 0.3, atol=0.05)
    assert np.all((cal.translation_rms_m > 0.0015) & (cal.translation_rms_m < 0.0025))
    assert np.all(cal.rotation_std_deg < 0.1) and np.all(cal.translation_std_m < 0.001)
    assert np.all(rot_err < 5 * cal.rotation_std_deg + 0.01)
    assert cal.heading_rad.shape == (inputs[0].shape[0],) and cal.drift.shape == (inputs[0].shape[0], 3)
    json.dumps(cal.as_dict(), allow_nan=False)


def test_mount_calibration_maps_between_worlds():
    inputs, _ = mount_scene(2)
    t, seg_rot, seg_pos, trk_rot, trk_pos, valid = inputs
    cal = calibrate_mounts(*inputs)
    # the suit segment mapped into the tracker world matches the segment implied by its tracker
    rot_w, pos_w = cal.suit_to_tracker_world(t, seg_rot, seg_pos)
    assert rot_w.shape == seg_rot.shape and pos_w.shape == seg_pos.shape
    k = 3
    ok = valid[:, k] & ~cal.outliers[:, k]
    rot_k, pos_k = cal.segment_from_tracker(trk_rot[ok, k], trk_pos[ok, k], k)
    ang = np.degrees((R.from_quat(rot_k).inv() * R.from_quat(rot_w[ok, k])).magnitude())
    assert np.median(ang) < 0.5 and np.percentile(np.linalg.norm(pos_k - pos_w[ok, k], axis=1), 95) < 0.005
    assert np.allclose(cal.heading_at(t), cal.heading_rad) and np.allclose(cal.drift_at(t), cal.drift)
    with pytest.raises(ValueError, match="tracker index 6 out of range"):
        cal.segment_from_tracker(trk_rot[:, 0], trk_pos[:, 0], 6)


def test_calibrate_mounts_flags_a_tracker_without_data():
    inputs, truth = mount_scene(3)
    t, seg_rot, seg_pos, trk_rot, trk_pos, valid = inputs
    valid = valid.copy()
    valid[:, 2] = False
    cal = calibrate_mounts(t, seg_rot, seg_pos, trk_rot, trk_pos, valid)
    assert cal.calibrated.tolist() == [True, True, False, True, True, True]
    assert np.isnan(cal.rotations[2]).all() and np.isnan(cal.translations[2]).all()
    assert np.isnan(cal.rotation_std_deg[2]) and np.isnan(cal.translation_rms_m[2])
    rot_err = np.degrees((R.from_quat(cal.rotations[[0, 1, 3, 4, 5]]).inv() * truth["mounts"][[0, 1, 3, 4, 5]])
                         .magnitude())  # fmt: skip
    assert rot_err.max() < 0.3
    assert cal.as_dict()["calibrated"][2] is False and cal.as_dict()["rotations_xyzw"][2] == [None] * 4
    with pytest.raises(ValueError, match="not calibrated"):
        cal.segment_from_tracker(trk_rot[:, 2], trk_pos[:, 2], 2)


def test_calibrate_mounts_static_single_segment_still_answers_with_large_std():
    inputs, _ = mount_scene(4, K=1)
    t, seg_rot, seg_pos, trk_rot, trk_pos, valid = inputs
    seg_rot = np.repeat(seg_rot[:1], t.shape[0], axis=0)  # the segment never rotates
    cal = calibrate_mounts(t, seg_rot, seg_pos, trk_rot, trk_pos, valid)
    assert np.isfinite(cal.translations).all() and cal.translation_std_m[0] > 0.1


def test_calibrate_mounts_ten_minutes():
    inputs, truth = mount_scene(5, duration=600.0, rate=30.0)
    cal = calibrate_mounts(*inputs)
    assert np.degrees(np.sqrt(np.mean((cal.heading_rad - truth["psi"]) ** 2))) < 0.1


def still_actor(seed, duration=20.0, rate=30.0):
    """Six trackers at their protocol sites (+1 cm) on an actor who stands still: segments sway
    by ~2 degrees, the suit's orientations carry 1-degree Gauss-Markov noise (tau 0.16 s), heading
    30 degrees plus 1 degree/min, tracker noise 0.3 degrees / 1 mm."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    T, K = t.shape[0], 6
    sites = np.array([TRACKER_SITES[g] for g in ("Pelvis", "Head", "LeftHand", "RightHand", "LeftFoot", "RightFoot")])
    places = np.array([(0, 1.0, 0), (0, 1.6, 0), (0.25, 1.0, 0.02), (-0.25, 1.0, 0.02), (0.1, 0.08, 0), (-0.1, 0.08, 0)])
    upright = R.from_matrix(np.column_stack([[0, 0, 1], [1, 0, 0], [0, 1, 0]]))  # segment x forward, z up
    base = [upright * R.from_rotvec(rng.normal(0, 0.2, 3)) for _ in range(K)]
    a = math.exp(-1 / (rate * 0.16))
    noise = np.zeros((T, K, 3))
    kick = rng.normal(0, math.radians(1) / math.sqrt(3) * math.sqrt(1 - a * a), (T, K, 3))
    for i in range(1, T):
        noise[i] = a * noise[i - 1] + kick[i]
    sway = math.radians(2) * np.sin(2 * np.pi * 0.2 * t)[:, None, None] * rng.normal(0, 1, (1, K, 3))
    seg_pos = places[None] + 0.005 * np.sin(2 * np.pi * 0.3 * t)[:, None, None]
    mounts = R.from_rotvec(rng.normal(0, math.radians(10) / math.sqrt(3), (K, 3)))
    offsets = sites + rng.normal(0, 0.01, (K, 3))
    psi = math.radians(30) + math.radians(1) / 60 * t
    Y = R.from_rotvec(psi[:, None] * np.array([0, 1.0, 0]))
    seg_rot, trk_rot, trk_pos = np.empty((T, K, 4)), np.empty((T, K, 4)), np.empty((T, K, 3))
    for k in range(K):
        true_seg = R.from_rotvec(sway[:, k]) * base[k]
        seg_rot[:, k] = (R.from_rotvec(noise[:, k]) * true_seg).as_quat()
        trk_rot[:, k] = (Y * true_seg * mounts[k] * R.from_rotvec(rng.normal(0, math.radians(0.3) / math.sqrt(3), (T, 3)))).as_quat()
        trk_pos[:, k] = Y.apply(seg_pos[:, k] + true_seg.apply(offsets[k])) + [1.0, 0, -2.0] + rng.normal(0, 0.001, (T, 3))
    return (t, seg_rot, seg_pos, trk_rot, trk_pos, np.ones((T, K), bool)), {"psi": psi, "mounts": mounts, "sites": sites,
                                                                           "offsets": offsets}  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_still_actors_heading_comes_from_the_tracker_sites(seed):
    inputs, truth = still_actor(seed)
    cal = calibrate_mounts(*inputs, sites=truth["sites"])
    err = abs(math.degrees(float(np.mean(cal.heading_rad - truth["psi"]))))
    std = float(cal.heading_std_deg)
    assert err < 1.0 and 0.3 < std < 3.0 and err < 3 * std, (err, std)
    rot_err = np.degrees((R.from_quat(cal.rotations).inv() * truth["mounts"]).magnitude())
    assert rot_err.max() < 1.5
    # the heading's uncertainty is part of every mount's: no longer a 0.1-degree claim
    assert np.all(cal.rotation_std_deg >= std) and cal.as_dict()["heading_std_deg"] == pytest.approx(std)
    without = calibrate_mounts(*inputs)
    assert float(without.heading_std_deg) == 0.0 and float(without.heading_offset_deg) == 0.0


def test_tracker_sites_leave_a_turning_actor_to_its_data():
    inputs, truth = mount_scene(1, rate=30.0)
    sites = truth["offsets"] + np.random.default_rng(0).normal(0, 0.01, truth["offsets"].shape)
    cal = calibrate_mounts(*inputs, sites=sites)
    assert np.degrees(np.sqrt(np.mean((cal.heading_rad - truth["psi"]) ** 2))) < 0.1
    assert float(cal.heading_std_deg) < 0.3
    rot_err = np.degrees((R.from_quat(cal.rotations).inv() * truth["mounts"]).magnitude())
    assert rot_err.max() < 0.3
    with pytest.raises(ValueError, match=r"sites must be finite with shape \(6, 3\)"):
        calibrate_mounts(*inputs, sites=sites[:5])
    with pytest.raises(ValueError, match="site_prior_m must be positive"):
        calibrate_mounts(*inputs, sites=sites, site_prior_m=0.0)


def test_the_trackers_common_offset_is_known_from_turning_segments_only():
    """The part all offsets share (where the root is) cannot be told from the suit's drift while no
    segment turns: it then rests on the sites' 2 cm prior, ~14 mm for six trackers (the simulated
    handshakes: 14-16 mm); this actor's 2-degree sway gives ~5 mm, segments turning freely 0.1 mm."""
    inputs, truth = still_actor(0)
    still = calibrate_mounts(*inputs, sites=truth["sites"])
    inputs, truth = mount_scene(1, rate=30.0)
    turning = calibrate_mounts(*inputs, sites=truth["offsets"])
    c_still, c_turning = float(still.common_offset_std_m), float(turning.common_offset_std_m)
    assert 3e-3 < c_still < 16e-3 and c_turning < 1e-3 and c_still > 20 * c_turning, (c_still, c_turning)
    assert still.as_dict()["common_offset_std_mm"] == pytest.approx(float(still.common_offset_std_m) * 1000, abs=1e-3)


def _carried(truth, K=6, rot_deg=0.2, offset_mm=2.0, seed=7, moved=None):
    """Mounts as a calibration take would hand them over: the truth off by ``rot_deg`` and
    ``offset_mm`` (per axis), with those as their stated 1-sigma; ``moved``: a tracker whose carried
    rotation is 10 degrees off (strapped again since)."""
    rng = np.random.default_rng(seed)
    rots = truth["mounts"] * R.from_rotvec(rng.normal(0, math.radians(rot_deg) / math.sqrt(3), (K, 3)))
    if moved is not None:
        q = rots.as_quat()
        q[moved] = (rots[moved] * R.from_rotvec([0.0, 0.0, math.radians(10.0)])).as_quat()
        rots = R.from_quat(q)
    offsets = truth["offsets"] + rng.normal(0, offset_mm / 1000, (K, 3))
    return CarriedMounts(np.ones(K, bool), rots.as_quat(), offsets, np.full(K, rot_deg), np.full(K, offset_mm * math.sqrt(3) / 1000),
                         source="calibration")  # fmt: skip


@pytest.mark.parametrize("seed", [0, 1])
def test_a_still_actor_keeps_the_mounts_of_a_calibration_take(seed):
    """Standing still, an actor's heading and its trackers' shared offset rest on the sites' 2 cm
    prior (~1 degree, ~14 mm): the mounts of the studio day's calibration take fix both. The
    carried rotations are kept as they are; the heading comes from them, to their spread over
    sqrt(6); the offsets stay within the calibration's millimetres."""
    inputs, truth = still_actor(seed)
    alone = calibrate_mounts(*inputs, sites=truth["sites"])
    carried = _carried(truth)
    cal = calibrate_mounts(*inputs, sites=truth["sites"], carried=carried)
    assert cal.carried.all() and not cal.carry_rejected.any()
    assert np.allclose(np.abs(np.sum(cal.rotations * carried.rotations, axis=1)), 1.0)  # kept as carried
    err = abs(math.degrees(float(np.mean(cal.heading_rad - truth["psi"]))))
    assert err < 0.15 and float(cal.heading_std_deg) == pytest.approx(0.2 / math.sqrt(6))
    common = [np.linalg.norm(np.mean(c.translations - truth["offsets"], axis=0)) for c in (cal, alone)]
    # (this actor's 2-degree sway tells the data ~5 mm of it; the calibration's 4 mm-per-axis floor,
    # CARRIED_FLOOR_M, lets the data still count)
    assert float(cal.common_offset_std_m) < 0.6 * float(alone.common_offset_std_m)
    assert common[0] < common[1] and common[0] < 2 * float(cal.common_offset_std_m), common
    assert np.linalg.norm(cal.translations - truth["offsets"], axis=1).max() < 0.008
    d = cal.as_dict()
    assert d["carried"] == [True] * 6 and d["carry_rejected"] == [False] * 6
    json.dumps(d, allow_nan=False)


def test_a_tracker_strapped_again_since_the_calibration_is_solved_afresh():
    inputs, truth = still_actor(0)
    carried = _carried(truth, moved=2)
    cal = calibrate_mounts(*inputs, sites=truth["sites"], carried=carried)
    assert cal.carry_rejected.tolist() == [False, False, True, False, False, False]
    assert cal.carried.tolist() == [True, True, False, True, True, True]
    rot_err = np.degrees((R.from_quat(cal.rotations).inv() * truth["mounts"]).magnitude())
    assert rot_err[2] < 1.0 and rot_err.max() < 1.0, rot_err  # the moved one from this take, the heading from the rest
    assert abs(math.degrees(float(np.mean(cal.heading_rad - truth["psi"])))) < 0.3
    assert MOVED_DEG < 10.0


def test_carried_mounts_are_picked_by_tracker_and_checked():
    inputs, truth = mount_scene(1, rate=30.0)
    cal = calibrate_mounts(*inputs)
    keys = [(f"S{k}", f"seg{k}") for k in range(6)]
    # this take: tracker S5 now on another segment, a new tracker S9, S0..S3 in another order
    mine = [keys[3], keys[0], ("S5", "other"), keys[2], ("S9", "seg9"), keys[1]]
    c = CarriedMounts.from_calibration(cal, keys, mine, "T001")
    assert c.carried.tolist() == [True, True, False, True, False, True] and c.source == "T001"
    assert np.array_equal(c.rotations[0], cal.rotations[3]) and np.array_equal(c.translations[5], cal.translations[1])
    assert np.isnan(c.rotations[2]).all() and np.isnan(c.translation_std_m[4])
    with pytest.raises(ValueError, match="carried mounts are for 6 trackers"):
        calibrate_mounts(*[a[:, :5] if getattr(a, "ndim", 1) > 1 else a for a in inputs], carried=c)
    bad = CarriedMounts(c.carried, c.rotations * 2, c.translations, c.rotation_std_deg, c.translation_std_m)
    with pytest.raises(ValueError, match="unit quaternions"):
        calibrate_mounts(*inputs, carried=bad)
    # nothing carried: the same answer as without
    none = CarriedMounts.from_calibration(cal, keys, [("X", "y")] * 6)
    again = calibrate_mounts(*inputs, carried=none)
    assert np.array_equal(again.rotations, cal.rotations) and np.array_equal(again.translations, cal.translations)
    assert not again.carried.any()


def test_a_turning_actors_heading_follows_its_orientations_over_a_skewed_constellation():
    """Orientations (0.3 deg noise, segments turning) say the heading is psi; the tracker positions
    were made 2 degrees further round (a systematic error the position model cannot absorb). The
    heading search must weigh the orientation residuals at their own scale (as measured at the
    heading the orientations chose, not at the edge of its +-20 degree grid, where they are tens of
    degrees and the orientations would count for nothing): the heading stays within 0.5 degrees."""
    inputs, truth = mount_scene(1, rate=30.0)
    t, seg_rot, seg_pos, trk_rot, trk_pos, valid = inputs
    skew = R.from_rotvec([0.0, math.radians(2.0), 0.0])
    centre = np.nanmean(trk_pos, axis=1, keepdims=True)
    trk_pos = centre + skew.apply((trk_pos - centre).reshape(-1, 3)).reshape(trk_pos.shape)
    trk_pos[np.all(inputs[4] == 0.0, axis=-1)] = 0.0  # the origin jumps stay at the origin
    cal = calibrate_mounts(t, seg_rot, seg_pos, trk_rot, trk_pos, valid, sites=truth["offsets"])
    err = math.degrees(float(np.mean(cal.heading_rad - truth["psi"])))
    assert abs(err) < 0.5, err


def chain_scene(seed, duration=20.0, rate=30.0):
    """Three suit segments in a chain, root -> arm -> hand, trackers on the root and the hand. The
    arm's measured orientation is the true one turned by a constant ``eps`` (3, -4, 2 degrees), and
    the suit places the hand at the end of the arm's bone (0, 0.3, 0.05) m turned by the measured
    orientation (an inertial suit's forward kinematics): ~20 mm off where it really is."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, duration, 1.0 / rate)
    T, S = t.shape[0], 3
    f, ph, amp = rng.uniform(0.1, 0.6, (S, 3)), rng.uniform(0, 2 * np.pi, (S, 3)), rng.uniform(0.4, 1.0, (S, 3))
    rv = amp * np.sin(2 * np.pi * f * t[:, None, None] + ph)
    true = [R.from_rotvec(rv[:, s]) for s in range(S)]
    eps = np.radians([3.0, -4.0, 2.0])
    meas = [true[0], true[1] * R.from_rotvec(eps), true[2]]
    bones = [None, np.array([0.1, 0.2, 0.0]), np.array([0.0, 0.3, 0.05])]
    root = np.array([0.0, 1.0, 0.0]) + 0.3 * np.sin(2 * np.pi * 0.1 * t)[:, None] * [1.0, 0.2, 0.5]

    def chain(rots):
        pos = [root]
        for s in (1, 2):
            pos.append(pos[-1] + rots[s - 1].apply(bones[s]))
        return np.stack(pos, 1)

    p_true, p_meas = chain(true), chain(meas)
    q_meas = np.stack([r.as_quat() for r in meas], 1)
    tracked = [0, 2]
    mounts = R.from_rotvec(rng.normal(0, 0.1, (2, 3)))
    offsets = np.array([TRACKER_SITES["Pelvis"], TRACKER_SITES["RightHand"]]) + rng.normal(0, 0.01, (2, 3))
    Y = R.from_rotvec([0.0, math.radians(30.0), 0.0])
    trk_rot = np.stack([(Y * true[s] * mounts[i]).as_quat() for i, s in enumerate(tracked)], 1)
    trk_pos = np.stack([Y.apply(p_true[:, s] + true[s].apply(offsets[i])) for i, s in enumerate(tracked)], 1)
    trk_pos += np.array([1.0, 0.0, -2.0]) + rng.normal(0, 0.001, trk_pos.shape)
    inputs = (t, q_meas[:, tracked], p_meas[:, tracked], trk_rot, trk_pos, np.ones((T, 2), bool))
    chain_model = SuitChain.of(q_meas, p_meas, tracked, [-1, 0, 1], prior_deg=3.0)
    return inputs, chain_model, {"offsets": offsets, "eps": eps, "bone": bones[2]}


@pytest.mark.parametrize("seed", [0, 1])
def test_the_suits_segment_misalignment_is_solved_with_the_mounts(seed):
    inputs, chain, truth = chain_scene(seed)
    assert chain.paths == ((), ((0, 1), (1, 2))) and chain.segments == (0, 1)
    cal = calibrate_mounts(*inputs, chain=chain)
    without = calibrate_mounts(*inputs)
    err = np.linalg.norm(cal.translations - truth["offsets"], axis=1)
    err_without = np.linalg.norm(without.translations - truth["offsets"], axis=1)
    # without the chain the mounts absorb the arm's error; with it they are within a millimetre
    assert err.max() < 0.001 and err_without.max() > 0.005, (err, err_without)
    assert cal.chain_segments.tolist() == [0, 1] and cal.chain_misalignment_rad.shape == (2, 3)
    # the root's (not misaligned) stays at zero; the arm's is seen through what it does to the hand:
    # the turn about the bone itself moves nothing and stays with the prior
    assert np.degrees(np.abs(cal.chain_misalignment_rad[0])).max() < 0.2
    moved = np.cross(cal.chain_misalignment_rad[1], truth["bone"]) - np.cross(truth["eps"], truth["bone"])
    assert np.linalg.norm(moved) < 0.001
    assert np.all(cal.chain_std_deg > 0) and np.all(cal.translation_std_m < 0.003)
    d = cal.as_dict()
    assert d["chain_segments"] == [0, 1] and np.allclose(d["chain_misalignment_deg"], np.degrees(cal.chain_misalignment_rad))
    json.dumps(d, allow_nan=False)
    assert without.chain_segments.size == 0 and without.as_dict()["chain_misalignment_deg"] == []


def test_suit_chain_errors():
    inputs, chain, _ = chain_scene(0, duration=4.0)
    with pytest.raises(ValueError, match="chain has paths for 1 trackers, not 2"):
        calibrate_mounts(*inputs, chain=SuitChain(chain.rot, chain.pos, chain.paths[:1]))
    with pytest.raises(ValueError, match=r"chain rot/pos must have shapes \(T=120, S, 4\)"):
        calibrate_mounts(*inputs, chain=SuitChain(chain.rot[:-1], chain.pos[:-1], chain.paths))
    with pytest.raises(ValueError, match="chain prior_deg must be positive"):
        calibrate_mounts(*inputs, chain=SuitChain(chain.rot, chain.pos, chain.paths, prior_deg=0.0))
    bad = chain.pos.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="chain pos has non-finite values"):
        calibrate_mounts(*inputs, chain=SuitChain(chain.rot, bad, chain.paths))
    with pytest.raises(ValueError, match="parents have a cycle"):
        SuitChain.of(chain.rot, chain.pos, [2], [1, 2, 0])


def test_calibrate_mounts_errors():
    inputs, _ = mount_scene(6, duration=4.0)
    t, seg_rot, seg_pos, trk_rot, trk_pos, valid = inputs
    short = valid.copy()
    short[60:] = False  # 1.5 s at 40 Hz
    with pytest.raises(ValueError, match="only 1.50 s of valid data; need at least 2"):
        calibrate_mounts(t, seg_rot, seg_pos, trk_rot, trk_pos, short)
    with pytest.raises(ValueError, match=r"seg_pos must have shape \(T=160, K, 3\)"):
        calibrate_mounts(t, seg_rot, seg_pos[:, :, :2], trk_rot, trk_pos, valid)
    with pytest.raises(ValueError, match="trk_pos has 5 trackers"):
        calibrate_mounts(t, seg_rot, seg_pos, trk_rot, trk_pos[:, :5], valid)
    with pytest.raises(ValueError, match="valid must be a bool array"):
        calibrate_mounts(t, seg_rot, seg_pos, trk_rot, trk_pos, valid.astype(int))
    bad = seg_pos.copy()
    bad[5, 0] = np.nan
    v = valid.copy()
    v[5, 0] = True
    with pytest.raises(ValueError, match="seg_pos has non-finite values at valid samples"):
        calibrate_mounts(t, seg_rot, bad, trk_rot, trk_pos, v)
    with pytest.raises(ValueError, match="times_s must increase strictly"):
        calibrate_mounts(t[::-1], seg_rot, seg_pos, trk_rot, trk_pos, valid)


def test_the_heading_search_scales_orientation_residuals_per_axis():
    """The orientation residuals' robust scale is a per-axis sigma, as the positions' is (the
    heading search sums squared 3-D residuals over it): for normal residuals of 0.01 rad per axis
    it reads ~0.01, not the 0.023 that 1.4826 x the median angle gives (which would weigh the
    orientations 5.2x too little against the tracker constellation); no inliers: 1.0."""
    from dualhuman_builder.sync.mount_constellation import axis_sigma

    rng = np.random.default_rng(3)
    rv = rng.normal(0.0, 0.01, (4000, 3, 3))
    rv[::10, 1] = 0.5  # outliers, left out by the inlier mask
    inl = np.ones((4000, 3), bool)
    inl[::10, 1] = False
    inl[:, 2] = False
    sig = axis_sigma(rv, inl)
    np.testing.assert_allclose(sig[:2], 0.01, rtol=0.05)
    assert sig[2] == 1.0
    assert 1.4826 * np.median(np.linalg.norm(rv[:, 0], axis=-1)) > 2.2 * sig[0]  # the angle's scale

"""Realistic tracker errors: each statistic is measured back from the generated samples (reported
minus true positions, valid flags, host and device stamps) and compared with the ranges the module
documents (:data:`~dualhuman_builder.sim.trackers.REALISTIC_RANGES`); the defaults (``ideal``) stay
bit-identical to the simulator without these errors."""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.sim.kinematics import DeviceClock, KinematicSpline
from dualhuman_builder.sim.trackers import (REALISTIC_RANGES, TrackerErrorModel, realistic_tracker_clock,
                                            simulate_trackers)  # fmt: skip
from dualhuman_builder.tracks import SkeletonTrack

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_sim_devices import analytic_pose, make_track  # noqa: E402
from stream_digest import stream_digest  # noqa: E402

#: Every error switched off: the terms under test are switched on one by one.
QUIET = TrackerErrorModel(position_noise_m=0.0, orientation_noise_deg=0.0, velocity_noise_m_s=0.0,
                          angular_velocity_noise_rad_s=0.0, loss_rate_per_min=0.0)  # fmt: skip
#: Both lighthouse stations on the hugger's side, in front of the partner (who faces +Z at the origin).
FRONT_STATIONS = ((1.5, 2.5, 2.5), (-1.5, 2.5, 2.5))
HAND_SITE = {"H-LHAND": "LeftHand"}

NAMES = ("device_time_ns", "host_time_ns", "valid", "position", "orientation", "velocity", "angular_velocity",
         "lost", "loss_tracker", "loss_start_ns", "loss_stop_ns", "loss_mode", "mount_rotation", "mount_translation")
#: Digests of streams recorded from the simulator before the realistic errors existed (same numpy/scipy).
BEFORE = {"default": "c24bd1532c57785e", "ideal": "2b633a25cc7593a0", "lossy": "433c9ad413e1b20c",
          "clock": "4799d2acc57940ae"}  # fmt: skip


def digest(stream) -> str:
    return stream_digest(stream, NAMES)


def track_from(t: np.ndarray, shift: np.ndarray, actor: str) -> SkeletonTrack:
    """The analytic T-pose skeleton (facing +Z, arms along X) translated by ``shift (T, 3)``."""
    quat, pos, _ = analytic_pose(t)
    ns = np.round(t * 1e9).astype(np.int64)
    return SkeletonTrack(MVN_SEGMENTS, quat, pos + shift[:, None, :], ns, ns, actor=actor, fps=30.0)


def smoothstep(t, t0, t1):
    x = np.clip((t - t0) / (t1 - t0), 0.0, 1.0)
    return x * x * (3 - 2 * x)


def hug_like(partner_x: float = 0.0):
    """A partner standing at ``(partner_x, 0, 0)`` facing +Z, and a hugger whose left wrist comes from
    the partner's side to 20 cm behind the partner's back at t = 1.5 s, stays until 3.5 s, and
    leaves by 4 s (6 s at 30 fps)."""
    t = np.arange(181) / 30.0
    partner = track_from(t, np.tile([partner_x, 0.0, 0.0], (len(t), 1)), "partner")
    # the T-pose's left wrist sits at (0.71, 1.45, 0): move it to x(t), 1.2 m high, z = -0.2
    x = 0.8 - 0.8 * smoothstep(t, 1.0, 1.5) + 0.8 * smoothstep(t, 3.5, 4.0)
    hugger = track_from(t, np.stack([x - 0.71, np.full_like(t, -0.25), np.full_like(t, -0.2)], 1), "hugger")
    return KinematicSpline(hugger), KinematicSpline(partner)


@pytest.fixture(scope="module")
def hug():
    return hug_like()


def runs(mask: np.ndarray) -> list[tuple[int, int]]:
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


# ------------------------------------------------------------------------------ ideal
def test_ideal_defaults_are_bit_identical_to_the_simulator_before_realistic_errors(hug):
    tr = make_track(duration_s=2.0, fps=30.0, yaw_rate=0.5, velocity=(0.3, 0, 0.1), wave=0.6, bob=0.02)
    clock = DeviceClock(offset_s=1.5, drift_ppm=-40, latency_s=0.02, jitter_s=0.003)
    got = {"default": digest(simulate_trackers(tr, seed=3)),
           "ideal": digest(simulate_trackers(tr, errors=TrackerErrorModel.ideal(), seed=3)),
           "lossy": digest(simulate_trackers(tr, errors=TrackerErrorModel(loss_rate_per_min=120.0,
                                                                          loss_origin_fraction=0.5), seed=5)),
           "clock": digest(simulate_trackers(tr, {"A": "Pelvis", "B": "LeftHand"}, rate_hz=120.0, seed=1,
                                             clock=clock))}  # fmt: skip
    assert got == BEFORE
    # the ideal model ignores the partner's body: no stations, no strap slip
    hugger, partner = hug
    plain, near = (simulate_trackers(hugger, HAND_SITE, seed=2, occluder=o) for o in (None, partner))
    assert digest(plain) == digest(near) and not near.hidden.any() and not near.mount_slip.any()


# ------------------------------------------------------------------------------ the draws
def test_realistic_draws_differ_across_seeds_within_their_ranges():
    models = [TrackerErrorModel.realistic(np.random.default_rng(s)) for s in range(12)]
    for m in models:
        for name, (lo, hi) in REALISTIC_RANGES.items():
            if hasattr(m, name):
                assert lo <= getattr(m, name) <= hi, name
        # two stations at opposite corners of a square room, above head height
        a, b = np.asarray(m.stations)
        np.testing.assert_allclose(a, b * [-1, 1, -1], atol=1e-12)
        assert 2.2 <= a[1] <= 2.8 and 1.5 * math.sqrt(2) - 1e-9 <= np.hypot(a[0], a[2]) <= 2.5 * math.sqrt(2) + 1e-9
        assert m.correlated_error_m > 0 and m.frame_tilt_deg > 0 and m.occlusion_enabled
    for name in ("correlated_error_m", "acquisition_offset_m", "frame_tilt_deg", "field_seed", "stations",
                 "reacquire_delay_s", "strap_slip_m"):  # fmt: skip
        assert len({repr(getattr(m, name)) for m in models}) == len(models), name
    again = TrackerErrorModel.realistic(np.random.default_rng(3))
    assert again == models[3]
    clocks = [realistic_tracker_clock(np.random.default_rng(s)) for s in range(12)]
    assert len({c.latency_s for c in clocks}) == len({c.drift_ppm for c in clocks}) == 12


def test_realistic_tracker_clock_latency_jitter_and_drift_measured_from_the_stamps():
    gt = KinematicSpline(make_track(10.0, fps=10.0))
    for s in range(3):
        clock = realistic_tracker_clock(np.random.default_rng(s))
        # at 50 Hz the arrival order hardly ever holds a sample back behind the one before
        tr = simulate_trackers(gt, {"P": "Pelvis"}, rate_hz=50.0, errors=QUIET, seed=s, clock=clock)
        delay = (tr.host_time_ns[0] - tr.true_time_ns) * 1e-9
        latency, jitter = np.quantile(delay, 0.001), delay.mean() - np.quantile(delay, 0.001)
        assert 0.015 - 1e-4 <= latency <= 0.030 + 1e-4  # around Niehorster et al.'s 22 ms
        assert 0.0008 <= jitter <= 0.0045
        slope, intercept = np.polyfit(tr.true_time_ns * 1e-9, tr.device_time_ns * 1e-9, 1)
        assert abs((slope - 1) * 1e6) <= 50.5 and 0.0 <= intercept <= 10.0


# ------------------------------------------------------------------------------ correlated error
@pytest.mark.parametrize("seed", [0, 5])
def test_correlated_error_rms_and_correlation_time_are_in_their_documented_ranges(seed):
    drawn = TrackerErrorModel.realistic(np.random.default_rng(seed))
    # the correlated error and the jitter alone, on a body standing still for a minute
    errors = dataclasses.replace(QUIET, position_noise_m=drawn.position_noise_m,
                                 correlated_error_m=drawn.correlated_error_m,
                                 correlated_error_tau_s=drawn.correlated_error_tau_s,
                                 vertical_ratio=drawn.vertical_ratio)  # fmt: skip
    sites = {f"T{i}": s for i, s in enumerate(("Pelvis", "Head", "LeftHand", "RightHand", "LeftFoot", "RightFoot"))}
    tr = simulate_trackers(make_track(60.0, fps=10.0), sites, rate_hz=50.0, errors=errors, seed=seed)
    err = tr.position - tr.true_position  # zero-mean here: no offsets, field or tilt
    rms = math.sqrt(np.mean(np.sum(err**2, axis=-1)))
    assert 0.0045 <= rms <= 0.0105  # 5-10 mm (Merker et al. 2023; Sansone et al. 2021)
    assert abs(rms / math.hypot(drawn.correlated_error_m, math.sqrt(3) * drawn.position_noise_m) - 1) < 0.2
    horizontal, vertical = err[..., [0, 2]].std(), err[..., 1].std()
    assert abs(vertical / horizontal / drawn.vertical_ratio - 1) < 0.25
    # correlation time from the autocovariance at lags of 0.4 and 0.8 s (their ratio leaves the jitter out)
    x = err.transpose(0, 2, 1).reshape(-1, err.shape[1])
    cov = [np.sum(x[:, lag:] * x[:, :-lag]) for lag in (20, 40)]
    tau = -0.4 / math.log(cov[1] / cov[0])
    lo, hi = REALISTIC_RANGES["correlated_error_tau_s"]
    assert 0.7 * lo <= tau <= 1.3 * hi and abs(tau / drawn.correlated_error_tau_s - 1) < 0.35


# ------------------------------------------------------------------------------ occlusion and re-acquisition
def test_a_wrist_behind_the_partners_back_is_lost_for_seconds(hug):
    hugger, partner = hug
    errors = dataclasses.replace(QUIET, stations=FRONT_STATIONS, reacquire_delay_s=0.3)
    tr = simulate_trackers(hugger, HAND_SITE, errors=errors, seed=1, occluder=partner)
    t = tr.true_time_ns * 1e-9
    lost = ~tr.valid[0]
    spells = runs(lost)
    assert len(spells) == 1
    first, stop = spells[0]
    assert 1.0 < t[first] < 1.6 and 3.5 < t[stop - 1] < 4.4 and t[stop - 1] - t[first] >= 2.0  # seconds long
    # it comes back reacquire_delay_s after it is seen again, reporting the last pose while lost
    seen = runs(tr.hidden[0])[0][1]
    assert abs(t[stop] - t[seen] - 0.3) < 2 / tr.rate_hz
    held = np.broadcast_to(tr.position[0, first - 1], (stop - first, 3))
    np.testing.assert_array_equal(tr.position[0, first:stop], held)
    assert list(tr.loss_cause) == ["hidden"] and list(tr.loss_mode) == ["invalid"]


def test_nothing_is_lost_when_nothing_occludes(hug):
    hugger, _ = hug
    errors = dataclasses.replace(QUIET, stations=FRONT_STATIONS, reacquire_delay_s=0.3)
    _, far = hug_like(partner_x=3.0)  # the partner three metres to the side
    for occluder in (far, None):
        tr = simulate_trackers(hugger, HAND_SITE, errors=errors, seed=1, occluder=occluder)
        assert tr.valid.all() and not tr.hidden.any() and len(tr.loss_tracker) == 0


def test_the_offset_changes_after_every_reacquisition(hug):
    hugger, partner = hug
    errors = dataclasses.replace(QUIET, stations=FRONT_STATIONS, reacquire_delay_s=0.2, acquisition_offset_m=0.01)
    tr = simulate_trackers(hugger, HAND_SITE, errors=errors, seed=4, occluder=partner)
    err = (tr.position - tr.true_position)[0]
    (first, stop), = runs(~tr.valid[0])
    before, after = err[:first], err[stop:]
    np.testing.assert_allclose(before, before[:1].repeat(len(before), 0), atol=1e-12)  # constant per acquisition
    np.testing.assert_allclose(after, after[:1].repeat(len(after), 0), atol=1e-12)
    assert np.linalg.norm(after[0] - before[0]) > 0.002
    # over many random losses the offsets have the documented 3-D RMS
    gt = KinematicSpline(make_track(20.0, fps=10.0))
    lossy = dataclasses.replace(QUIET, loss_rate_per_min=60.0, acquisition_offset_m=0.01, vertical_ratio=2.0)
    tr = simulate_trackers(gt, {f"T{i}": "Pelvis" for i in range(10)}, rate_hz=50.0, errors=lossy, seed=2)
    offsets = []
    for i in range(10):
        e = (tr.position - tr.true_position)[i]
        for a, b in runs(tr.valid[i] & ~tr.lost[i]):
            offsets.append(e[a:b].mean(axis=0))
    offsets = np.array(offsets)
    assert len(offsets) > 150
    assert abs(math.sqrt(np.mean(np.sum(offsets**2, axis=1))) / 0.01 - 1) < 0.15
    assert abs(offsets[:, 1].std() / offsets[:, [0, 2]].std() / 2.0 - 1) < 0.25


# ------------------------------------------------------------------------------ jumps, tilt, field, slip
def test_jumps_are_centimetres_long_and_never_to_the_origin():
    gt = KinematicSpline(make_track(20.0, fps=10.0, velocity=(0.1, 0.0, 0.0)))
    errors = dataclasses.replace(QUIET, jump_rate_per_min=30.0)
    tr = simulate_trackers(gt, {f"T{i}": "Head" for i in range(6)}, rate_hz=100.0, errors=errors, seed=3)
    size = np.linalg.norm(tr.position - tr.true_position, axis=-1)
    jumped = size > 1e-9
    assert tr.valid.all()
    assert 0.01 - 1e-9 <= size[jumped].min() and size[jumped].max() <= 0.05 + 1e-9
    assert np.linalg.norm(tr.position, axis=-1).min() > 1.0  # the head never lands at the origin
    spells = [s for i in range(6) for s in runs(jumped[i])]
    minutes = 6 * 20.0 / 60
    assert 0.5 * 30 * minutes < len(spells) < 1.5 * 30 * minutes
    assert all(b - a <= 0.2 * tr.rate_hz + 1 for a, b in spells)


def test_the_frame_tilt_shows_as_a_height_error_growing_with_horizontal_distance():
    t = np.arange(121) / 30.0
    walk = np.stack([np.zeros_like(t), np.zeros_like(t), -2.0 + t], 1)  # 4 m along +Z through the origin
    gt = KinematicSpline(track_from(t, walk, "walker"))
    errors = dataclasses.replace(QUIET, frame_tilt_deg=0.4, frame_tilt_azimuth_deg=0.0)  # tilt axis +X
    tr = simulate_trackers(gt, {"P": "Pelvis"}, errors=errors, seed=0)
    z = tr.true_position[0, :, 2]
    dy = (tr.position - tr.true_position)[0, :, 1]
    slope = np.polyfit(z, dy, 1)[0]
    assert abs(abs(math.degrees(math.atan(slope))) - 0.4) < 0.01
    far, near = np.abs(z) > 1.5, np.abs(z) < 0.3
    assert np.abs(dy[far]).min() > 0.009 and np.abs(dy[near]).max() < 0.003  # ~1 cm at 1.5 m, mm near the origin


def test_the_realistic_field_and_tilt_give_centimetres_across_the_room_and_millimetres_across_a_body():
    t = np.arange(121) / 30.0
    walk = np.stack([-1.5 + 0.75 * t, np.zeros_like(t), -1.5 + 0.75 * t], 1)  # 4.2 m across the room
    gt = KinematicSpline(track_from(t, walk, "walker"))
    spans, body = [], []
    for s in range(8):
        drawn = TrackerErrorModel.realistic(np.random.default_rng(s))
        errors = dataclasses.replace(QUIET, field_distortion_m=drawn.field_distortion_m, field_seed=drawn.field_seed,
                                     field_wavelength_m=drawn.field_wavelength_m, frame_tilt_deg=drawn.frame_tilt_deg,
                                     frame_tilt_azimuth_deg=drawn.frame_tilt_azimuth_deg)  # fmt: skip
        tr = simulate_trackers(gt, {"P": "Pelvis", "H": "Head"}, errors=errors, seed=0)
        err = tr.position - tr.true_position
        spans.append(np.linalg.norm(err[0].max(axis=0) - err[0].min(axis=0)))
        body.append(np.linalg.norm(err[1] - err[0], axis=-1).max())  # head and pelvis, 70 cm apart
    assert 0.01 < np.median(spans) < 0.1 and max(spans) < 0.15  # several centimetres over the room
    assert np.median(body) < 0.015


def test_straps_slip_under_contact_and_stay_slipped(hug):
    hugger, partner = hug
    errors = dataclasses.replace(QUIET, strap_slip_m=0.008, slip_contact_m=0.1)
    slips = []
    for seed in range(4):
        tr = simulate_trackers(hugger, HAND_SITE, rate_hz=60.0, errors=errors, seed=seed, occluder=partner)
        t = tr.true_time_ns * 1e-9
        moved = np.linalg.norm(tr.mount_slip[0], axis=-1)
        assert moved[t < 1.0].max() == 0.0  # no contact yet
        slips.append(moved[-1])
        assert moved[-1] == moved[(t > 4.2)].min()  # a strap does not slide back
        # the tracker really moves by the slip, and reports where it is
        still = simulate_trackers(hugger, HAND_SITE, rate_hz=60.0, errors=QUIET, seed=seed, occluder=partner)
        np.testing.assert_allclose(np.linalg.norm(tr.true_position[0] - still.true_position[0], axis=-1), moved,
                                   atol=1e-12)  # fmt: skip
        np.testing.assert_array_equal(tr.position, tr.true_position)
    slips = np.array(slips)
    assert 0.002 < np.median(slips) < 0.03 and slips.max() <= 0.03 + 1e-12
    assert not simulate_trackers(hugger, HAND_SITE, errors=errors, seed=0).mount_slip.any()  # no partner, no slip


def test_realistic_streams_stay_finite_and_mostly_valid_on_a_two_body_take(hug):
    hugger, partner = hug
    errors = TrackerErrorModel.realistic(np.random.default_rng(7))
    tr = simulate_trackers(hugger, occluder=partner, errors=errors, seed=7, clock=realistic_tracker_clock(
        np.random.default_rng(7)))  # fmt: skip
    assert np.isfinite(tr.position).all() and np.isfinite(tr.orientation).all()
    assert tr.valid.mean() > 0.5
    err = np.linalg.norm(tr.position - tr.true_position, axis=-1)[tr.valid & ~tr.lost]
    assert np.median(err) < 0.1
    for stations in (((0.0, 2.5),), (1.0, 2.5, 1.0), ((0.0, math.nan, 1.0),)):
        with pytest.raises(ValueError, match="stations"):
            TrackerErrorModel(stations=stations)
    assert TrackerErrorModel(stations=[[1, 2.5, 1]]).stations == ((1.0, 2.5, 1.0),)  # as read back from JSON
    with pytest.raises(ValueError, match="jump_size_m"):
        TrackerErrorModel(jump_size_m=(0.05, 0.01))

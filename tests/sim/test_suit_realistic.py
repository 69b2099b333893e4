"""The suit's realistic errors, measured back from the generated samples against the ground truth
and compared with the ranges documented in :mod:`dualhuman_builder.sim.suit`.

Ground truth is the analytic walking, turning, arm-waving skeleton of ``test_sim_devices``; the
suit samples at 60 Hz to keep the tests fast (the error processes do not depend on the rate).
"""

from __future__ import annotations

import dataclasses
import math
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as R

from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.sim.kinematics import KinematicSpline
from dualhuman_builder.sim.suit import SuitErrorModel, simulate_suit

sys.path.insert(0, str(Path(__file__).resolve().parent))

from test_sim_devices import angle_between, make_track, only  # noqa: E402
from stream_digest import stream_digest  # noqa: E402

RATE = 60.0
PAIRS = [(c, MVN_SEGMENTS.index(MVN_PARENTS[n])) for c, n in enumerate(MVN_SEGMENTS) if MVN_PARENTS[n] is not None]


@pytest.fixture(scope="module")
def moving():
    """20 s of a walking, turning, arm-waving skeleton at 60 fps, splined once."""
    return KinematicSpline(make_track(20.0, yaw_rate=0.4, velocity=(0.3, 0.0, -0.2), wave=0.6, bob=0.02))


def realistic(seed: int, **changes) -> SuitErrorModel:
    return dataclasses.replace(SuitErrorModel.realistic(np.random.default_rng(seed)), **changes)


def digest(stream) -> str:
    return stream_digest(stream, ("sample_counter", "time_code_ms", "device_time_ns", "host_time_ns", "orientations",
                                  "positions", "sensor_acc", "sensor_gyro", "sensor_mag"))


def test_default_errors_give_the_streams_they_always_gave():
    """The defaults (the ``ideal`` preset) reproduce, bit for bit, a stream recorded from the suit
    simulator before the realistic errors existed (same numpy/scipy on this machine)."""
    spline = KinematicSpline(make_track(2.0, yaw_rate=0.3, wave=0.4, velocity=(0.2, 0, 0)))
    suit = simulate_suit(spline, 1, seed=7)
    assert digest(suit) == "86c7d19cf3f63601"
    assert not suit.errors.realistic_errors_on and suit.soft_tissue is None and len(suit.dropout_start_ns) == 0


def test_the_suit_reports_its_own_skeleton(moving):
    """Segment lengths off by the documented 1-2 cm (one draw per left/right pair), constant over
    the take; joint centres off anny's by 1-3 cm across the bone."""
    length_err, across, total = [], [], []
    for seed in range(6):
        suit = simulate_suit(moving, rate_hz=RATE, errors=realistic(seed), seed=seed)
        err = {}
        for c, p in PAIRS:
            reported = np.linalg.norm(suit.positions[:, c] - suit.positions[:, p], axis=-1)
            true = np.linalg.norm(suit.truth.positions[:, c] - suit.truth.positions[:, p], axis=-1)
            assert np.ptp(reported - true) < 1e-6  # a rigid skeleton of its own
            total.append(float(np.mean(reported - true)))
            # the bone in the parent's reported frame against the truth's: the length error along it (the
            # measured dimension's), the joint-centre offset across it
            rel = R.from_quat(suit.orientations[0, p]).apply(suit.positions[0, c] - suit.positions[0, p], inverse=True)
            rel_true = R.from_quat(suit.truth.orientations[0, p]).apply(
                suit.truth.positions[0, c] - suit.truth.positions[0, p], inverse=True)  # fmt: skip
            u = rel_true / np.linalg.norm(rel_true)
            d = rel - rel_true
            err[MVN_SEGMENTS[c]] = float(d @ u)
            across.append(np.linalg.norm(d - u * (d @ u)))
        for name, e in err.items():  # MVN scales both sides from one measured dimension
            if name.startswith("Left"):
                assert abs(e - err[name.replace("Left", "Right")]) < 1e-6
        length_err += [e for n, e in err.items() if not n.startswith("Right")]
    assert 0.009 < math.sqrt(np.mean(np.square(total))) < 0.025  # what a fit sees: |length| reported - true
    rms = math.sqrt(np.mean(np.square(length_err)))
    assert 0.009 < rms < 0.022, rms  # documented: std U(1, 2) cm per take
    assert 0.4 < np.std(length_err) / rms <= 1.0  # errors of both signs
    rms_across = math.sqrt(np.mean(np.square(across)))
    assert 0.009 < rms_across < 0.033, rms_across  # documented: U(1, 3) cm


def test_dynamic_orientation_error_is_2_to_5_degrees_and_follows_the_motion(moving):
    arms = [MVN_SEGMENTS.index(s) for s in ("LeftUpperArm", "RightUpperArm", "LeftForeArm", "RightForeArm")]
    legs = [MVN_SEGMENTS.index(s) for s in ("LeftUpperLeg", "RightUpperLeg", "LeftLowerLeg", "RightLowerLeg")]
    rms_all = []
    for seed in range(5):
        model = realistic(seed, misalignment_deg=0.0, heading_drift_deg_per_min=0.0,
                          heading_drift_segment_deg_per_min=0.0, magnetic_episode_rate_per_min=0.0,
                          segment_length_sigma_m=0.0, joint_centre_offset_m=0.0, root_drift_m_per_sqrt_min=0.0,
                          root_drift_vertical_m_per_sqrt_min=0.0)  # fmt: skip
        suit = simulate_suit(moving, rate_hz=RATE, errors=model, seed=seed)
        ang = np.degrees(angle_between(suit.truth.orientations, suit.orientations))  # (T, 23)
        rms = math.sqrt(np.mean(ang**2))
        rms_all.append(rms)
        assert 1.8 < rms < 5.4, rms  # documented: U(2, 5) deg over the body
        assert rms == pytest.approx(math.hypot(model.orientation_noise_deg, model.soft_tissue_deg), rel=0.15)
        # soft tissue grows with the motion: the waving arms err more than the legs, which only turn with the body
        assert math.sqrt(np.mean(ang[:, arms] ** 2)) > 1.3 * math.sqrt(np.mean(ang[:, legs] ** 2))
    assert np.ptp(rms_all) > 0.5  # drawn per take


def test_segments_in_contact_err_more(moving):
    """A contact load on the left upper arm for the second half of the take raises its error there;
    the right arm, which moves the same, does not change."""
    model = realistic(3, misalignment_deg=0.0, heading_drift_deg_per_min=0.0, heading_drift_segment_deg_per_min=0.0,
                      magnetic_episode_rate_per_min=0.0, orientation_noise_deg=0.0,
                      soft_tissue_contact_gain=1.0)  # fmt: skip
    frames = moving.track.num_frames
    load = np.zeros((frames, 23))
    load[frames // 2:, MVN_SEGMENTS.index("LeftUpperArm")] = 1.0
    suit = simulate_suit(moving, rate_hz=RATE, errors=model, seed=3, contact=load)
    ang = np.degrees(angle_between(suit.truth.orientations, suit.orientations))
    half = suit.true_time_ns * 1e-9 >= 10.0 + 0.2

    def rms(x):
        return math.sqrt(np.mean(x**2))

    left, right = MVN_SEGMENTS.index("LeftUpperArm"), MVN_SEGMENTS.index("RightUpperArm")
    assert rms(ang[half, left]) / rms(ang[~half, left]) > 1.5  # documented factor 1 + gain = 2
    assert 0.6 < rms(ang[half, right]) / rms(ang[~half, right]) < 1.5
    with pytest.raises(ValueError, match="contact must be"):
        simulate_suit(moving, rate_hz=RATE, errors=model, contact=load[:, :5])


def test_each_segment_drifts_in_heading_on_its_own(moving):
    slopes_std = []
    for seed in range(4):
        model = only(heading_drift_deg_per_min=realistic(seed).heading_drift_deg_per_min,
                     heading_drift_segment_deg_per_min=realistic(seed).heading_drift_segment_deg_per_min)  # fmt: skip
        suit = simulate_suit(moving, rate_hz=RATE, errors=model, seed=seed)
        err = R.from_quat(suit.orientations.reshape(-1, 4)) * R.from_quat(suit.truth.orientations.reshape(-1, 4)).inv()
        yaw = err.as_rotvec()[:, 1].reshape(len(suit), 23)  # world-frame heading error per segment
        t_min = suit.true_time_ns * 1e-9 / 60.0
        slopes = np.degrees(np.polyfit(t_min, yaw, 1)[0])  # deg/min per segment
        assert np.ptp(slopes) > 0.5  # not one ramp common to the body
        assert 0.5 * 0.6 < abs(np.mean(slopes)) < 2.0 + 3 * 2.0 / math.sqrt(23)  # common logU(0.5, 2) deg/min
        slopes_std.append(np.std(slopes))
        assert np.std(slopes) == pytest.approx(model.heading_drift_segment_deg_per_min, rel=0.45)
    assert 0.35 < np.mean(slopes_std) < 2.2  # documented: logU(0.5, 2) deg/min per segment


def test_magnetic_episodes_are_heading_bursts_lasting_seconds(moving):
    peak = realistic(5).magnetic_episode_peak_deg
    model = only(magnetic_episode_rate_per_min=12.0, magnetic_episode_peak_deg=peak, magnetic_episode_min_s=1.0,
                 magnetic_episode_max_s=8.0)  # many episodes in 20 s
    suit = simulate_suit(moving, rate_hz=RATE, errors=model, seed=5)
    err = R.from_quat(suit.orientations.reshape(-1, 4)) * R.from_quat(suit.truth.orientations.reshape(-1, 4)).inv()
    yaw = np.degrees(np.abs(err.as_rotvec()[:, 1].reshape(len(suit), 23)))
    on = yaw.max(axis=1) > 1e-6
    edges = np.flatnonzero(np.diff(np.r_[0, on.astype(int), 0]))
    spans = (edges[1::2] - edges[::2]) / RATE
    assert len(spans) >= 2
    assert spans.min() > 0.5 and spans.max() < 8.0 + 1e-6  # 1-8 s episodes (back to back ones join)
    assert 0.5 * peak < yaw.max() <= 2 * peak + 1e-9  # documented peak U(2, 10) deg; overlaps may add up
    assert 2.0 * 0.5 * 0.5 < np.percentile(yaw.max(axis=0), 50)
    assert np.ptp(yaw.max(axis=0)) > 0.05 * peak  # segments weighted differently


def test_dropouts_leave_gaps_of_a_tenth_to_one_second():
    spline = KinematicSpline(make_track(60.0, yaw_rate=0.2, wave=0.3, fps=30.0))
    gaps, takes_with = [], 0
    for seed in range(6):
        suit = simulate_suit(spline, rate_hz=RATE, errors=realistic(seed), seed=seed)
        steps = np.diff(suit.sample_counter)
        missing = steps[steps > 1] - 1
        gaps += list(missing / RATE)
        takes_with += bool(len(missing))
        # every per-sample array lost the same frames; the truth follows the kept ones
        n = len(suit)
        assert suit.orientations.shape[0] == suit.truth.num_samples == suit.sensor_acc.shape[0] == n
        assert suit.sensor_ideal.acc.shape[0] == suit.sensor_errors.acc_noise.shape[0] == n
        assert np.all(np.diff(suit.device_time_ns) > 0)
        assert len(suit.dropout_start_ns) >= len(missing)
    assert takes_with >= 2 and len(gaps) >= 3  # documented: U(0.5, 3) per minute
    assert 0.1 - 2 / RATE <= min(gaps) and max(gaps) <= 1.0 + 1 / RATE


def test_host_receives_the_suit_in_bursts(moving):
    for seed in range(3):
        model = realistic(seed)
        suit = simulate_suit(moving, rate_hz=240.0, errors=model, seed=seed)
        d = np.diff(suit.host_time_ns) * 1e-9
        assert np.mean(d == 0) > 0.5  # most frames arrive with another one
        period = np.median(d[d > 0.001])
        assert 0.01 - 0.002 < period < 0.1 + 0.01  # documented: logU(10, 100) ms
        assert period == pytest.approx(model.host_burst_period_s, rel=0.1)
        # never earlier than the frame was sent
        assert np.all(suit.host_time_ns >= suit.true_time_ns + suit.clock.latency_s * 1e9 - 1)


def test_realistic_draws_move_within_their_ranges():
    draws = [SuitErrorModel.realistic(np.random.default_rng(s)) for s in range(200)]
    dynamic = [math.hypot(d.orientation_noise_deg, d.soft_tissue_deg) for d in draws]
    assert 2.0 <= min(dynamic) and max(dynamic) <= 5.0 and np.ptp(dynamic) > 2.5
    for name, lo, hi in (("segment_length_sigma_m", 0.01, 0.02), ("joint_centre_offset_m", 0.01, 0.03),
                         ("heading_drift_segment_deg_per_min", 0.5, 2.0), ("dropout_rate_per_min", 0.5, 3.0),
                         ("magnetic_episode_peak_deg", 2.0, 10.0), ("host_burst_period_s", 0.01, 0.1)):  # fmt: skip
        values = [getattr(d, name) for d in draws]
        assert lo <= min(values) and max(values) <= hi and np.ptp(values) > 0.6 * (hi - lo), name
    assert all(d.realistic_errors_on for d in draws)
    with pytest.raises(ValueError, match="min <= max"):
        SuitErrorModel(dropout_rate_per_min=1.0, dropout_min_s=2.0, dropout_max_s=1.0)

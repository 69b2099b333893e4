"""Simulated devices: ground-truth resampling, IMU physics, suit and tracker error models, clocks.

Ground truth here is an analytic 23-segment skeleton (root translating and yawing, arms and legs
swinging) whose poses and rates are known in closed form at any time, plus one real track from the
body model. Statistics are estimated from the produced streams against that truth.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation as R

from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.capture.samples import ImuSample, SuitFrame, TrackerSample
from dualhuman_builder.conventions import GRAVITY
from dualhuman_builder.body.mapping import SEGMENT_TPOSE_FRAME
from dualhuman_builder.rig import TRACKER_SITES
from dualhuman_builder.sim.imu import (ImuNoiseModel, earth_magnetic_field, gauss_markov, imu_errors, simulate_imu,
                                       specific_force)  # fmt: skip
from dualhuman_builder.sim.kinematics import DeviceClock, KinematicSpline, resample
from dualhuman_builder.sim.suit import MVN_SENSOR_SEGMENTS, SuitErrorModel, simulate_suit
from dualhuman_builder.sim.trackers import (TrackerErrorModel, default_sites,
                                            simulate_trackers)  # fmt: skip
from dualhuman_builder.tracks import SkeletonTrack

G = -GRAVITY[1]
E_Y = np.array([0.0, 1.0, 0.0])
E_Z = np.array([0.0, 0.0, 1.0])

# Segment origin relative to its parent's origin in a body at identity orientation (world axes:
# +X left, +Y up, +Z forward), metres.
OFFSETS = {
    "Pelvis": (0.0, 0.95, 0.0), "L5": (0, .1, 0), "L3": (0, .1, 0), "T12": (0, .1, 0), "T8": (0, .1, 0),
    "Neck": (0, .15, 0), "Head": (0, .1, 0),
    "RightShoulder": (-.03, .1, 0), "RightUpperArm": (-.15, 0, 0), "RightForeArm": (-.28, 0, 0),
    "RightHand": (-.25, 0, 0), "LeftShoulder": (.03, .1, 0), "LeftUpperArm": (.15, 0, 0),
    "LeftForeArm": (.28, 0, 0), "LeftHand": (.25, 0, 0), "RightUpperLeg": (-.09, -.02, 0),
    "RightLowerLeg": (0, -.42, 0), "RightFoot": (0, -.42, 0), "RightToe": (0, -.07, .14),
    "LeftUpperLeg": (.09, -.02, 0), "LeftLowerLeg": (0, -.42, 0), "LeftFoot": (0, -.42, 0), "LeftToe": (0, -.07, .14),
}  # fmt: skip
WAVE_HZ = 0.5
BOB_HZ = 1.0


def analytic_pose(t, yaw_rate=0.0, velocity=(0.0, 0.0, 0.0), wave=0.0, bob=0.0):
    """Closed-form skeleton at times ``t (T,)`` s: root at (0, 0.95, 0) + velocity t (+ a vertical
    bob), yawing at ``yaw_rate`` about world +Y; upper arms swing about the parent's Z by
    ``wave sin(2 pi WAVE_HZ t)``. Returns quats (T, 23, 4), positions (T, 23, 3) and the world
    angular velocity (T, 23, 3)."""
    t = np.asarray(t, dtype=np.float64)
    A, P, W = {}, {}, {}
    for s in MVN_SEGMENTS:
        parent = MVN_PARENTS[s]
        if parent is None:
            A[s] = R.from_rotvec(np.outer(yaw_rate * t, E_Y))
            P[s] = np.asarray(OFFSETS[s]) + np.outer(t, velocity) + np.outer(bob * np.sin(2 * np.pi * BOB_HZ * t), E_Y)
            W[s] = np.tile(yaw_rate * E_Y, (len(t), 1))
            continue
        A[s], W[s] = A[parent], W[parent]
        if wave and s.endswith("UpperArm"):
            sign = 1.0 if s.startswith("Left") else -1.0
            w = 2 * np.pi * WAVE_HZ
            A[s] = A[parent] * R.from_rotvec(np.outer(sign * wave * np.sin(w * t), E_Z))
            W[s] = W[parent] + A[parent].apply(np.outer(sign * wave * w * np.cos(w * t), E_Z))
        P[s] = P[parent] + A[parent].apply(OFFSETS[s])
    B = R.from_matrix(SEGMENT_TPOSE_FRAME)
    quat = np.stack([(A[s] * B).as_quat() for s in MVN_SEGMENTS], 1)
    pos = np.stack([P[s] for s in MVN_SEGMENTS], 1)
    return quat, pos, np.stack([W[s] for s in MVN_SEGMENTS], 1)


def make_track(duration_s=4.0, fps=60.0, actor="synth", **motion) -> SkeletonTrack:
    t = np.arange(int(round(duration_s * fps)) + 1) / fps
    quat, pos, _ = analytic_pose(t, **motion)
    ns = np.round(t * 1e9).astype(np.int64)
    return SkeletonTrack(MVN_SEGMENTS, quat, pos, ns, ns, actor=actor, fps=fps)


def angle_between(q_a, q_b) -> np.ndarray:
    """Angle (rad) of ``R_a^T R_b`` for quaternion arrays (..., 4)."""
    a = R.from_quat(np.reshape(q_a, (-1, 4)))
    b = R.from_quat(np.reshape(q_b, (-1, 4)))
    return (a.inv() * b).magnitude().reshape(np.shape(q_a)[:-1])


def only(**fields) -> SuitErrorModel:
    """A suit error model with every error off except ``fields`` (ideal sensors)."""
    base = {k: 0.0 for k in SuitErrorModel.__dataclass_fields__ if k not in ("imu", "sensor_mount_deg")}
    return SuitErrorModel(**{**base, **fields}, imu=ImuNoiseModel.ideal())


@pytest.fixture(scope="module")
def moving():
    """10 s of a walking, turning, waving skeleton at 60 fps, splined once."""
    return KinematicSpline(make_track(10.0, yaw_rate=0.4, velocity=(0.3, 0.0, -0.2), wave=0.6, bob=0.02))


# ------------------------------------------------------------------------------ kinematics
def test_resample_reproduces_analytic_motion_and_its_derivatives(moving):
    kin = resample(moving, 240.0)
    assert kin.num_samples == 2401 and np.all(np.diff(kin.times_ns) > 0)
    t = kin.times_ns * 1e-9
    quat, pos, w_world = analytic_pose(t, yaw_rate=0.4, velocity=(0.3, 0.0, -0.2), wave=0.6, bob=0.02)
    assert np.abs(kin.positions - pos).max() < 1e-4
    assert angle_between(kin.orientations, quat).max() < 1e-4
    inner = slice(24, -24)  # spline end conditions need a few frames to settle
    assert np.abs(kin.angular_velocity_world - w_world)[inner].max() < 1e-4
    assert np.abs(kin.angular_velocity_world - w_world).max() < 1e-2
    # body-frame rate is the world rate seen from the segment
    rot = R.from_quat(kin.orientations.reshape(-1, 4))
    body = rot.apply(np.array(kin.angular_velocity_world).reshape(-1, 3), inverse=True)
    np.testing.assert_allclose(body.reshape(kin.angular_velocity_body.shape), kin.angular_velocity_body, atol=1e-12)
    # root velocity and acceleration in closed form
    pelvis = MVN_SEGMENTS.index("Pelvis")
    wb = 2 * np.pi * BOB_HZ
    v = np.array([0.3, 0.0, -0.2]) + np.outer(0.02 * wb * np.cos(wb * t), E_Y)
    a = np.outer(-0.02 * wb**2 * np.sin(wb * t), E_Y)
    assert np.abs(kin.velocity[inner, pelvis] - v[inner]).max() < 1e-3
    assert np.abs(kin.acceleration[inner, pelvis] - a[inner]).max() < 5e-3
    # a hand swept round the yaw axis: centripetal acceleration of the rigid-point formula
    p, vel, acc = kin.point(MVN_SEGMENTS.index("Head"), [0.0, 0.0, 0.1])
    np.testing.assert_allclose(np.gradient(p, t, axis=0)[inner], vel[inner], atol=2e-3)
    np.testing.assert_allclose(np.gradient(vel, t, axis=0)[inner], acc[inner], atol=2e-2)


def test_resample_window_and_bounds(moving):
    kin = resample(moving, 100.0, t0_ns=1_000_000_000, duration_s=2.0)
    np.testing.assert_array_equal(kin.times_ns, 1_000_000_000 + np.arange(201) * 10_000_000)
    with pytest.raises(ValueError, match="outside the track"):
        moving.evaluate([moving.t1_ns + 10_000_000])
    with pytest.raises(ValueError, match="invalid"):
        gt = make_track(1.0)
        bad = np.ones((gt.num_frames, 23), bool)
        bad[3, 2] = False
        KinematicSpline(SkeletonTrack(gt.segment_names, gt.orientations, gt.positions, gt.device_time_ns,
                                      gt.host_time_ns, position_valid=bad))  # fmt: skip


def test_device_clock_samples_on_its_own_clock():
    clock = DeviceClock(offset_s=2.0, drift_ppm=100.0, host_offset_s=50.0, latency_s=0.003, jitter_s=0.001)
    device, true = clock.sample_times(0, 10_000_000_000, 250.0)
    np.testing.assert_array_equal(np.diff(device), 4_000_000)  # regular on the device clock
    np.testing.assert_allclose(np.diff(true), 4e6 / (1 + 100e-6), rtol=1e-9)  # stretched in scene time
    assert device[0] == 2_000_000_000 and true[-1] <= 10_000_000_000
    host = clock.host_time_ns(true, np.random.default_rng(0))
    lag = (host - 50e9 - true) * 1e-9
    assert lag.min() >= 0.003 and abs(lag.mean() - 0.004) < 1e-4 and np.all(np.diff(host) >= 0)


# ------------------------------------------------------------------------------ IMU physics
def test_specific_force_is_zero_in_free_fall_and_reads_up_at_rest():
    q = R.random(5, random_state=1).as_quat()
    np.testing.assert_allclose(specific_force(q, np.tile(GRAVITY, (5, 1))), 0.0, atol=1e-12)
    up = R.from_quat(q).apply(np.tile([0.0, G, 0.0], (5, 1)), inverse=True)
    np.testing.assert_allclose(specific_force(q, np.zeros(3)), up, atol=1e-12)


def test_sensors_at_rest_read_gravity_up_and_the_earth_field():
    gt = make_track(1.0)
    suit = simulate_suit(gt, errors=only(), seed=4)
    quat, _, _ = analytic_pose(suit.true_time_ns * 1e-9)
    field = earth_magnetic_field()
    for i, seg in enumerate(MVN_SENSOR_SEGMENTS):
        r_ws = R.from_quat(quat[0, MVN_SEGMENTS.index(seg)]) * R.from_quat(suit.sensor_mount[i])
        up = r_ws.apply([0.0, G, 0.0], inverse=True)
        np.testing.assert_allclose(suit.sensor_acc[:, i], np.tile(up, (len(suit), 1)), atol=1e-9)
        np.testing.assert_allclose(suit.sensor_gyro[:, i], 0.0, atol=1e-12)
        np.testing.assert_allclose(suit.sensor_mag[:, i], np.tile(r_ws.apply(field, inverse=True), (len(suit), 1)),
                                   atol=1e-9)  # fmt: skip
    # the sensors sit at different angles on their segments, so they read gravity differently
    assert np.ptp(suit.sensor_acc[0], axis=0).max() > 1.0
    # a lone MTi, mounted upside down on the pelvis
    flip = R.from_rotvec([math.pi, 0.0, 0.0])
    mti = simulate_imu(gt, "Pelvis", 100.0, ImuNoiseModel.ideal(), mount_rotation=flip.as_quat())
    r_ws = R.from_matrix(SEGMENT_TPOSE_FRAME) * flip
    np.testing.assert_allclose(mti.acceleration, np.tile(r_ws.apply([0, G, 0], inverse=True), (len(mti), 1)), atol=1e-9)
    np.testing.assert_allclose(mti.acceleration[0], [0.0, 0.0, -G], atol=1e-9)  # its z axis points down


def test_gyro_and_accelerometer_of_a_body_turning_at_a_constant_rate():
    w = 1.2  # rad/s about world +Y, root standing still
    gt = make_track(3.0, yaw_rate=w)
    suit = simulate_suit(gt, errors=only(), seed=2)
    t = suit.true_time_ns * 1e-9
    B = R.from_matrix(SEGMENT_TPOSE_FRAME)
    root = np.asarray(OFFSETS["Pelvis"])
    _, pos0, _ = analytic_pose(np.zeros(1))
    inner = slice(30, -30)
    for i, seg in enumerate(MVN_SENSOR_SEGMENTS):
        s = MVN_SEGMENTS.index(seg)
        mount = R.from_quat(suit.sensor_mount[i])
        gyro = (B * mount).apply([0.0, w, 0.0], inverse=True)  # constant in the sensor frame
        np.testing.assert_allclose(suit.sensor_gyro[:, i], np.tile(gyro, (len(t), 1)), atol=1e-6)
        # the sensor circles the vertical through the root: centripetal -w^2 r_horizontal
        c = pos0[0, s] - root + B.apply(np.array(suit.sensor_lever_arm[i]))
        yaw = R.from_rotvec(np.outer(w * t, E_Y))
        r = yaw.apply(c) * np.array([1.0, 0.0, 1.0])
        r_ws = yaw * B * mount
        expected = r_ws.apply(-w * w * r - GRAVITY, inverse=True)
        np.testing.assert_allclose(suit.sensor_acc[inner, i], expected[inner], atol=2e-3)


def test_imu_noise_follows_its_densities_and_biases():
    noise = ImuNoiseModel(gyro_bias_sigma=0.01, acc_bias_sigma=0.05, gyro_bias_walk=0.002, acc_bias_walk=0.01)
    for rate in (400.0, 100.0):
        err = imu_errors(np.random.default_rng(7), 2000, 300, rate, noise)
        ratio = np.std(err.gyro_noise) / (noise.gyro_noise_density * math.sqrt(rate / 2))
        assert abs(ratio - 1) < 0.01
        assert abs(np.std(err.acc_noise) / (noise.acc_noise_density * math.sqrt(rate / 2)) - 1) < 0.01
        assert abs(np.std(err.gyro_bias[0]) / 0.01 - 1) < 0.1 and abs(np.std(err.acc_bias[0]) / 0.05 - 1) < 0.1
        # the bias walks: its spread after T samples grows as walk * sqrt(T / rate)
        span = math.sqrt(1999 / rate)
        assert abs(np.std(err.gyro_bias[-1] - err.gyro_bias[0]) / (0.002 * span) - 1) < 0.1
        assert abs(np.std(err.acc_bias[-1] - err.acc_bias[0]) / (0.01 * span) - 1) < 0.1
    constant = imu_errors(np.random.default_rng(7), 500, 4, 400.0, ImuNoiseModel())
    assert np.all(constant.gyro_bias == constant.gyro_bias[0]) and np.all(constant.acc_bias == constant.acc_bias[0])


def test_mti_stream_counter_clock_and_orientation_error():
    gt = make_track(6.0, yaw_rate=0.3, wave=0.4)
    clock = DeviceClock(offset_s=0.5, drift_ppm=40.0)
    mti = simulate_imu(gt, "LeftForeArm", 400.0, ImuNoiseModel(), seed=3, clock=clock, first_counter=65000)
    samples = list(mti)
    assert all(isinstance(s, ImuSample) for s in samples) and len(samples) == len(mti) > 2300
    counters = np.array([s.counter for s in samples])
    assert counters[0] == 65000 and counters.max() == 65535 and np.all(np.diff(counters) % 65536 == 1)
    assert np.all(np.diff(mti.device_time_ns) == 25 * 100_000)  # 25 ticks of the 10 kHz clock
    assert np.all(mti.device_time_ns % 100_000 == 0)
    np.testing.assert_allclose(mti.true_time_ns, clock.true_time_ns(mti.device_time_ns), atol=1)
    # the reported orientation is the truth, turned by the heading offset and the filter error
    expected = R.from_rotvec([0.0, mti.heading_offset_rad, 0.0]) * R.from_quat(mti.true_orientation) \
        * R.from_rotvec(np.array(mti.orientation_error))
    assert angle_between(mti.orientation, expected.as_quat()).max() < 1e-9
    err = np.degrees(angle_between(mti.true_orientation, (R.from_quat(mti.true_orientation)
                                                          * R.from_rotvec(np.array(mti.orientation_error))).as_quat()))
    assert 0.3 < np.sqrt(np.mean(err**2)) < 0.7  # 0.5 deg RMS, correlated over 0.16 s
    with pytest.raises(ValueError, match="SampleTimeFine"):
        simulate_imu(gt, "Pelvis", 240.0)


def test_gauss_markov_has_its_std_and_correlation_time():
    x = gauss_markov(np.random.default_rng(0), 20000, (50,), 2.0, 0.1, 0.01)
    assert abs(np.std(x) / 2.0 - 1) < 0.03
    lag = 10  # one correlation time
    rho = np.mean(x[lag:] * x[:-lag]) / np.mean(x * x)
    assert abs(rho - math.exp(-1)) < 0.03


# ------------------------------------------------------------------------------ suit
def test_suit_orientation_noise_is_as_configured_and_the_skeleton_stays_connected(moving):
    suit = simulate_suit(moving, errors=only(orientation_noise_deg=1.0, orientation_noise_tau_s=0.16), seed=11)
    err = np.degrees(angle_between(suit.truth.orientations, suit.orientations))
    assert abs(np.sqrt(np.mean(err**2)) - 1.0) < 0.08
    # correlated like a filtered estimate: one correlation time (0.16 s) later, e^-1 left
    x = suit.orientation_noise
    lag = round(0.16 * 240)
    assert abs(np.mean(x[lag:] * x[:-lag]) / np.mean(x * x) - math.exp(-1)) < 0.08
    # root exact, every bone keeps its true length
    np.testing.assert_allclose(suit.positions[:, 0], suit.truth.positions[:, 0], atol=1e-12)
    for c, name in enumerate(MVN_SEGMENTS[1:], start=1):
        p = MVN_SEGMENTS.index(MVN_PARENTS[name])
        length = np.linalg.norm(suit.positions[:, c] - suit.positions[:, p], axis=-1)
        true_length = np.linalg.norm(suit.truth.positions[:, c] - suit.truth.positions[:, p], axis=-1)
        np.testing.assert_allclose(length, true_length, atol=1e-9)
    hand = MVN_SEGMENTS.index("LeftHand")
    assert 0.002 < np.linalg.norm(suit.positions[:, hand] - suit.truth.positions[:, hand], axis=-1).mean() < 0.05


def test_suit_heading_drift_rate_is_as_configured(moving):
    rate = 30.0  # deg/min, with the default orientation noise and misalignment on top
    suit = simulate_suit(moving, errors=SuitErrorModel(heading_drift_deg_per_min=rate), seed=5)
    err = R.from_quat(suit.orientations.reshape(-1, 4)) * R.from_quat(suit.truth.orientations.reshape(-1, 4)).inv()
    yaw = err.as_rotvec()[:, 1].reshape(len(suit), 23).mean(axis=1)  # world-frame error about +Y
    t = suit.true_time_ns * 1e-9
    slope = np.polyfit(t, yaw, 1)[0]
    assert abs(abs(np.degrees(slope) * 60) - rate) < 0.05 * rate
    assert np.sign(slope) == np.sign(suit.heading_drift_rate_rad_s)
    # the whole body turns about the root: positions relative to the pelvis rotate with it
    clean = simulate_suit(moving, errors=only(heading_drift_deg_per_min=rate), seed=5)
    yaw_rot = R.from_rotvec(np.outer(clean.heading_drift_rad, E_Y))
    rel_true = clean.truth.positions - clean.truth.positions[:, :1]
    for s in (6, 14, 22):
        np.testing.assert_allclose(clean.positions[:, s] - clean.positions[:, 0], yaw_rot.apply(rel_true[:, s]),
                                   atol=1e-9)  # fmt: skip
    assert abs(np.degrees(clean.heading_drift_rad[-1]) - np.sign(slope) * rate / 6) < 1e-6  # 10 s of drift


def test_suit_root_drift_is_a_random_walk_of_the_configured_scale(moving):
    suit = simulate_suit(moving, errors=only(root_drift_m_per_sqrt_min=0.05, root_drift_vertical_m_per_sqrt_min=0.01),
                         seed=8)  # fmt: skip
    drift = suit.positions - suit.truth.positions
    np.testing.assert_allclose(drift, np.broadcast_to(drift[:, :1], drift.shape), atol=1e-12)  # whole skeleton
    np.testing.assert_allclose(drift[:, 0], suit.root_drift, atol=1e-12)
    steps = np.diff(drift[:, 0], axis=0)
    span_min = (suit.true_time_ns[-1] - suit.true_time_ns[0]) * 1e-9 / 60
    scale = np.sqrt(np.sum(steps**2, axis=0) / span_min)  # m per sqrt(minute), per axis
    np.testing.assert_allclose(scale, [0.05, 0.01, 0.05], rtol=0.06)
    for axis in range(3):  # independent increments: a random walk, not a smooth drift
        s = steps[:, axis]
        assert abs(np.mean(s[1:] * s[:-1]) / np.mean(s * s)) < 0.1


def test_suit_misalignment_is_constant_per_segment_with_the_configured_spread():
    gt = make_track(1.0, yaw_rate=0.5, wave=0.5)
    spline = KinematicSpline(gt)
    angles = []
    for seed in range(6):
        suit = simulate_suit(spline, errors=only(misalignment_deg=3.0), seed=seed)
        err = R.from_quat(suit.truth.orientations.reshape(-1, 4)).inv() * R.from_quat(suit.orientations.reshape(-1, 4))
        err = err.as_quat().reshape(len(suit), 23, 4)
        err *= np.sign(err[..., 3:])
        np.testing.assert_allclose(err, np.broadcast_to(err[:1], err.shape), atol=1e-9)  # constant in time
        np.testing.assert_allclose(err[0], suit.misalignment * np.sign(suit.misalignment[:, 3:]), atol=1e-12)
        angles.append(np.degrees(R.from_quat(err[0]).magnitude()))
    rms = np.sqrt(np.mean(np.concatenate(angles) ** 2))
    assert abs(rms - 3.0) < 0.45  # 138 draws: ~5% standard error


def test_suit_frames_counters_and_clock_recovered_from_the_motion():
    v = 0.5
    gt = make_track(8.0, velocity=(v, 0.0, 0.0))
    clock = DeviceClock(offset_s=1.5, drift_ppm=50.0, host_offset_s=100.0, latency_s=0.003, jitter_s=0.001)
    suit = simulate_suit(gt, character=3, errors=only(), seed=1, clock=clock)
    frames = list(suit)
    assert all(isinstance(f, SuitFrame) for f in frames) and len(frames) == len(suit)
    assert [f.sample_counter for f in frames] == list(range(len(frames)))
    assert {f.character for f in frames} == {3} and frames[0].segment_names == MVN_SEGMENTS
    device = np.array([f.device_time_ns for f in frames])
    assert np.abs(np.diff(device) - 1e9 / 240).max() <= 1  # 240 Hz on the suit's own clock
    np.testing.assert_array_equal([f.time_code_ms for f in frames], (device - device[0]) // 1_000_000)
    # scene time of each frame from the pelvis' travel alone; then the clock's offset and drift
    x = np.array([f.positions[0, 0] for f in frames])
    t = x / v
    slope, intercept = np.polyfit(t, device * 1e-9, 1)
    assert abs((slope - 1) * 1e6 - 50.0) < 0.05 and abs(intercept - 1.5) < 1e-6
    host = np.array([f.host_time_ns for f in frames]) * 1e-9
    lag = host - 100.0 - t
    assert lag.min() >= 0.003 - 1e-6 and abs(lag.mean() - 0.004) < 2e-4 and np.all(np.diff(host) >= 0)
    track = suit.to_track()
    assert track.fps == 240.0 and track.num_frames == len(suit)
    np.testing.assert_array_equal(track.host_time_ns, suit.host_time_ns)


# ------------------------------------------------------------------------------ trackers
def test_tracker_noise_is_as_configured_and_mounts_are_realistic(moving):
    errors = TrackerErrorModel(position_noise_m=0.002, orientation_noise_deg=0.5, loss_rate_per_min=0.0)
    trackers = simulate_trackers(moving, errors=errors, seed=2)
    assert trackers.serials == tuple(default_sites("SYNTH"))
    err = trackers.position - trackers.true_position
    np.testing.assert_allclose(err.reshape(-1, 3).std(axis=0), 0.002, rtol=0.03)
    assert abs(np.abs(err.mean()) / 0.002) < 0.02
    ang = np.degrees(angle_between(trackers.true_orientation, trackers.orientation))
    assert abs(np.sqrt(np.mean(ang**2)) - 0.5) < 0.015
    # the truth is the analytic segment pose carrying the mount
    quat, pos, _ = analytic_pose(trackers.true_time_ns * 1e-9, yaw_rate=0.4, velocity=(0.3, 0.0, -0.2), wave=0.6,
                                 bob=0.02)  # fmt: skip
    for i, seg in enumerate(trackers.segments):
        s = MVN_SEGMENTS.index(seg)
        r_seg = R.from_quat(quat[:, s])
        mount_at = r_seg.apply(np.array(trackers.mount_translation[i]))
        np.testing.assert_allclose(trackers.true_position[i], pos[:, s] + mount_at, atol=2e-4)
        mounted = (r_seg * R.from_quat(trackers.mount_rotation[i])).as_quat()
        assert angle_between(trackers.true_orientation[i], mounted).max() < 2e-4
        # a few cm off the segment origin, on the surface side of its nominal site
        m, nominal = trackers.mount_translation[i], np.asarray(TRACKER_SITES[seg])
        assert 0.02 < np.linalg.norm(m) < 0.25 and np.linalg.norm(m - nominal) < 0.05
        assert np.dot(m, nominal) > 0
    assert trackers.mount_translation[trackers.index("SYNTH-PELVIS"), 0] < -0.05  # on the back


def test_tracker_loss_rate_durations_and_modes_match_config():
    gt = KinematicSpline(make_track(20.0, velocity=(0.1, 0.0, 0.1)))
    sites = {f"T{i:02d}": MVN_SEGMENTS[i % 23] for i in range(30)}
    errors = TrackerErrorModel(loss_rate_per_min=60.0, loss_duration_s=(0.02, 0.4), loss_origin_fraction=0.4)
    tr = simulate_trackers(gt, sites, errors=errors, seed=9)
    period = 1.0 / tr.rate_hz
    # detect losses from what the trackers report: invalid flags, or valid poses at the origin
    at_origin = np.all(tr.position == 0.0, axis=-1) & np.all(tr.orientation == [0, 0, 0, 1], axis=-1)
    lost = ~tr.valid | at_origin
    np.testing.assert_array_equal(lost, tr.lost)
    # an invalid flag holds the last tracked pose (the origin only before anything was tracked)
    assert not np.any(~tr.valid & at_origin & (np.cumsum(~lost, axis=1) > 0))
    i, k = np.argwhere(~tr.valid & (np.cumsum(~lost, axis=1) > 0))[0]
    last = np.flatnonzero(~lost[i, :k])[-1]
    np.testing.assert_array_equal(tr.position[i, k], tr.position[i, last])
    runs, durations, origin_runs = 0, [], 0
    for i in range(len(tr.serials)):
        edges = np.flatnonzero(np.diff(np.concatenate([[0], lost[i].astype(int), [0]])))
        for start, stop in zip(edges[::2], edges[1::2]):
            runs += 1
            origin_runs += bool(at_origin[i, start])
            if 0 < start and stop < lost.shape[1]:
                durations.append((stop - start) * period)
    tracked_min = (~lost).sum() * period / 60
    assert abs(runs / tracked_min / 60.0 - 1) < 0.15  # ~560 events: Poisson error ~4%
    d = np.array(durations)
    # (two events a sample apart read as one run, so bound the bulk, not the maximum)
    assert d.min() >= 0.02 - period and np.quantile(d, 0.99) <= 0.4 + period
    # log-uniform: the mean log duration is the midpoint of the log range
    assert abs(np.mean(np.log(d)) - np.mean(np.log([0.02, 0.4]))) < 0.12
    assert abs(origin_runs / runs - 0.4) < 0.08
    # the record of events agrees with the samples
    assert len(tr.loss_tracker) >= runs and set(tr.loss_mode) == {"invalid", "origin"}
    for i, start, stop, mode in zip(tr.loss_tracker, tr.loss_start_ns, tr.loss_stop_ns, tr.loss_mode):
        inside = (tr.true_time_ns >= start) & (tr.true_time_ns < stop)
        assert tr.lost[i, inside].all()
        assert (tr.valid[i, inside] == (mode == "origin")).all()


def test_tracker_clock_offset_and_drift_recovered_from_the_motion():
    v = 0.4
    gt = make_track(10.0, velocity=(v, 0.0, 0.0))
    clock = DeviceClock(offset_s=0.37, drift_ppm=80.0, host_offset_s=20.0, latency_s=0.004, jitter_s=0.002)
    tr = simulate_trackers(gt, {"P": "Pelvis", "H": "LeftHand"}, errors=TrackerErrorModel.ideal(), seed=1, clock=clock)
    np.testing.assert_array_equal(np.diff(tr.device_time_ns), 4_000_000)  # 250 Hz on the tracker clock
    _, pos0, _ = analytic_pose(np.zeros(1))
    B = R.from_matrix(SEGMENT_TPOSE_FRAME)
    for i, seg in enumerate(tr.segments):
        # a body translating without turning: each tracker is its segment origin plus a fixed offset
        c = pos0[0, MVN_SEGMENTS.index(seg), 0] + B.apply(np.array(tr.mount_translation[i]))[0]
        t = (tr.position[i, :, 0] - c) / v
        slope, intercept = np.polyfit(t, tr.device_time_ns * 1e-9, 1)
        assert abs((slope - 1) * 1e6 - 80.0) < 0.05 and abs(intercept - 0.37) < 1e-6
        lag = tr.host_time_ns[i] * 1e-9 - 20.0 - t
        assert lag.min() >= 0.004 - 1e-6 and abs(lag.mean() - 0.006) < 4e-4
    samples = list(tr)
    assert all(isinstance(s, TrackerSample) for s in samples) and len(samples) == 2 * tr.valid.shape[1]
    hosts = [s.host_time_ns for s in samples]
    assert hosts == sorted(hosts)
    for serial in ("P", "H"):
        dev = [s.device_time_ns for s in samples if s.serial == serial]
        assert np.all(np.diff(dev) > 0)


# ------------------------------------------------------------------------------ seeds, truth, real body
def _arrays(obj):
    return {k: v for k, v in vars(obj).items() if isinstance(v, np.ndarray)}


def test_equal_seeds_give_identical_streams_and_different_seeds_differ():
    spline = KinematicSpline(make_track(2.0, yaw_rate=0.3, wave=0.4))
    trackers_err = TrackerErrorModel(loss_rate_per_min=30.0)
    a, b = simulate_suit(spline, 1, seed=7), simulate_suit(spline, 1, seed=7)
    for k, v in _arrays(a).items():
        np.testing.assert_array_equal(v, _arrays(b)[k], err_msg=k)
    assert not np.array_equal(a.orientations, simulate_suit(spline, 1, seed=8).orientations)
    assert not np.array_equal(a.orientations, simulate_suit(spline, 2, seed=7).orientations)  # other actor
    # each error process has its own random stream: switching the others off leaves it as it was
    alone = simulate_suit(spline, 1, errors=only(orientation_noise_deg=1.0, orientation_noise_tau_s=0.16), seed=7)
    np.testing.assert_array_equal(alone.orientation_noise, a.orientation_noise)
    ta = simulate_trackers(spline, errors=trackers_err, seed=7)
    tb = simulate_trackers(spline, errors=trackers_err, seed=7)
    for k, v in _arrays(ta).items():
        np.testing.assert_array_equal(v, _arrays(tb)[k], err_msg=k)
    assert [(s.serial, s.host_time_ns) for s in ta] == [(s.serial, s.host_time_ns) for s in tb]
    tc = simulate_trackers(spline, errors=trackers_err, seed=8)
    assert not np.array_equal(ta.position, tc.position)
    assert not np.array_equal(ta.mount_translation, tc.mount_translation)
    # a tracker's realisation depends on its serial, not on the other trackers
    solo = simulate_trackers(spline, {"SYNTH-HEAD": "Head"}, errors=trackers_err, seed=7)
    np.testing.assert_array_equal(solo.position[0], ta.position[ta.index("SYNTH-HEAD")])
    ia, ib = simulate_imu(spline, "Head", seed=7), simulate_imu(spline, "Head", seed=7)
    np.testing.assert_array_equal(ia.acceleration, ib.acceleration)
    assert not np.array_equal(ia.acceleration, simulate_imu(spline, "Head", seed=8).acceleration)


def greeting_sequence(model, shapes: list[dict], frames: int = 60, fps: float = 30.0, distance_m: float = 1.2):
    """Two bodies facing each other ``distance_m`` apart (along Z), feet on the floor, raising
    their arms from the rest A-pose to a T-pose with eased timing. Returns an InteractionSequence."""
    import torch

    from dualhuman_builder.body.joints import tpose
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    s = 0.5 - 0.5 * np.cos(np.pi * np.linspace(0.0, 1.0, frames))  # ease in/out, 0 -> 1
    tracks = []
    for i, shape in enumerate(shapes):
        shape_t = model.shape_tensor(shape)
        with torch.no_grad():
            target = tpose(model, shape_t).cpu().numpy()  # (J, 3) rotation vectors from rest
            floor = -float(model.rest(shape_t).vertices[0, :, 1].min())  # lift the soles onto y = 0
        pose = s[:, None, None] * target[None]  # rotvec scaling from zero is exact slerp
        facing = np.array([0.0, np.pi * i, 0.0])  # actor 1 turned 180 degrees about +Y
        pose[:, 0] = facing
        z = (-0.5 if i == 0 else 0.5) * distance_m
        transl = np.tile([0.0, floor, z], (frames, 1))
        tracks.append(BodyTrack.from_model(model, pose, transl, shape_t.cpu().numpy(), fps, actor=f"actor{i}"))
    return InteractionSequence(tuple(tracks), take="T", labels=("demo",),
                               text=("Two people face each other and spread their arms.",))  # fmt: skip


@pytest.fixture(scope="module")
def body_gt(body_model):
    from dualhuman_builder.sim.groundtruth import segment_kinematics

    seq = greeting_sequence(body_model, [None, None], frames=60)
    return segment_kinematics(seq.actors[0], model=body_model)


def test_devices_on_a_body_model_track_leave_the_ground_truth_intact(body_gt):
    before = {k: np.array(v) for k, v in _arrays(body_gt).items()}
    spline = KinematicSpline(body_gt)
    suit = simulate_suit(body_gt, seed=1)
    trackers = simulate_trackers(spline, seed=1)
    mti = simulate_imu(spline, "T8", 100.0, seed=1)
    for k, v in _arrays(body_gt).items():
        np.testing.assert_array_equal(v, before[k], err_msg=k)
        assert not v.flags.writeable
    # truth kept with the streams equals the ground truth at its own frames
    np.testing.assert_allclose(resample(body_gt, body_gt.fps).positions, body_gt.positions, atol=1e-9)
    kin = spline.evaluate(suit.true_time_ns)
    order = [body_gt.segment_index(s) for s in MVN_SEGMENTS]
    np.testing.assert_allclose(suit.truth.positions, kin.positions[:, order], atol=1e-12)
    # plausible errors: cm positions, a degree or two of orientation
    assert len(suit) == 473 and suit.positions.shape == (473, 23, 3)
    pos_err = np.linalg.norm(suit.positions - suit.truth.positions, axis=-1)
    assert 0.001 < pos_err.mean() < 0.05
    ang = np.degrees(angle_between(suit.truth.orientations, suit.orientations))
    assert 0.5 < np.sqrt(np.mean(ang**2)) < 4.0
    # only the arms move: sensors on the trunk and legs feel 1 g throughout, the arm sensors more
    still = [i for i, s in enumerate(MVN_SENSOR_SEGMENTS) if "Arm" not in s and "Hand" not in s]
    np.testing.assert_allclose(np.linalg.norm(suit.sensor_acc[:, still], axis=-1).mean(axis=0), G, atol=0.02)
    assert np.linalg.norm(suit.sensor_acc, axis=-1).max() > G + 0.1
    assert abs(np.linalg.norm(mti.acceleration, axis=-1).mean() - G) < 0.02
    # trackers: six per actor, a few cm off their segment origins, valid most of the time
    assert trackers.serials == tuple(default_sites(body_gt.actor.upper()))
    seg_pos = spline.evaluate(trackers.true_time_ns).positions
    for i, seg in enumerate(trackers.segments):
        off = np.linalg.norm(trackers.true_position[i] - seg_pos[:, body_gt.segment_index(seg)], axis=-1)
        assert 0.02 < off.min() and off.max() < 0.25
    good = trackers.valid & ~trackers.lost
    assert np.abs(trackers.position - trackers.true_position)[good].max() < 0.01


def test_bad_inputs_are_refused():
    gt = make_track(1.0)
    partial = SkeletonTrack(MVN_SEGMENTS[:5], gt.orientations[:, :5], gt.positions[:, :5], gt.device_time_ns,
                            gt.host_time_ns)  # fmt: skip
    with pytest.raises(ValueError, match="lacks MVN segments"):
        simulate_suit(partial)
    with pytest.raises(KeyError, match="no segment"):
        simulate_trackers(gt, {"X": "Tail"})
    with pytest.raises(ValueError, match="non-negative"):
        SuitErrorModel(orientation_noise_deg=-1.0)
    with pytest.raises(ValueError, match="loss_duration_s"):
        TrackerErrorModel(loss_duration_s=(0.5, 0.1))
    with pytest.raises(ValueError, match="at least 2 frames"):
        KinematicSpline(SkeletonTrack(MVN_SEGMENTS, gt.orientations[:1], gt.positions[:1], gt.device_time_ns[:1],
                                      gt.host_time_ns[:1]))  # fmt: skip

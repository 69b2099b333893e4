"""Inertial measurement units strapped to body segments: ideal readings from ground-truth
kinematics, a noise and bias model, and the single MTi-style IMU stream of :class:`ImuSample`\\ s.

Measurement model, for a sensor on segment ``s`` with mounting rotation ``M`` (sensor frame in the
segment frame) and lever arm ``r`` (sensor origin in the segment frame, m); ``R_ws = R_seg M`` is
the sensor orientation (sensor-to-world):

* rate of turn ``gyro = M^T w_body + b_g(t) + n_g`` (rad/s, sensor frame);
* specific force ``acc = R_ws^T (a_r - g) + b_a(t) + n_a`` (m/s^2, sensor frame), ``a_r`` the world
  acceleration of the sensor origin (with the lever-arm terms, :meth:`Kinematics.point`) and
  ``g = conventions.GRAVITY = (0, -9.80665, 0)``: at rest a sensor reads +9.81 m/s^2 along world up;
* magnetic field ``mag = R_ws^T m_world + n_m`` (arbitrary units, 1 = the local earth field), from a
  fixed world field vector (:func:`earth_magnetic_field`); disturbances are not modelled.

Noise conventions (:class:`ImuNoiseModel`): white noise is given as a density ``n`` (unit/sqrt(Hz))
band-limited to the Nyquist frequency, so one sample at ``f_s`` has ``sigma = n * sqrt(f_s / 2)``.
This matches Xsens' own measurement (MTi at rest, accelerometer std 0.0137 m/s^2 at 400 Hz and
0.0068 m/s^2 at 100 Hz, i.e. about 100 ug/sqrt(Hz): Xsens knowledge base, "RMS noise of
accelerometers and gyroscopes"). Biases: a constant per run drawn ``N(0, sigma^2)`` per axis plus
an optional random walk ``b_{k+1} = b_k + q sqrt(dt) w_k``.

Default figures and where they come from:

* gyroscope noise density 0.007 deg/s/sqrt(Hz), accelerometer 120 ug/sqrt(Hz), gyroscope in-run
  bias stability 10 deg/h: Xsens MTi-1 series datasheet (as tabulated in "Characteristics of IMU
  Xsens MTi-1 sensors", Transport Problems/TAR 2023, doi:10.2478/tar-2023-0022). The MTw sensors of
  an MVN suit are of the same class; one default serves both.
* orientation output error of the MTi (:attr:`ImuSample.orientation`): 0.5 deg RMS (static
  roll/pitch accuracy 0.5 deg, dynamic 2 deg RMS) and a per-run heading offset of 1.0 deg (static
  heading accuracy): "MTi and MTx User Manual and Technical Documentation", Xsens MT0100P, section
  4.2. The error is low-frequency (a filtered estimate), modelled as a first-order Gauss-Markov
  process with 0.16 s correlation time, i.e. the ~1 Hz crossover of Xsens' fusion filter at its
  default gain (same manual, "Filter Gain").
* the constant turn-on biases (gyroscope 0.05 deg/s, accelerometer 0.005 m/s^2 per axis) and
  magnetometer noise (0.002 a.u.) are assumptions of ours, not published figures: residuals after
  the factory calibration and on-line bias estimation Xsens describe; set them from a real unit's
  Allan variance when one is at hand. The bias random walk is off by default.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
from scipy.signal import lfilter
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.conventions import GRAVITY
from dualhuman_builder.sim.kinematics import DeviceClock, Kinematics, KinematicSpline, as_spline
from dualhuman_builder.tracks import SkeletonTrack

#: One g, m/s^2 (for datasheet figures in ug).
STANDARD_GRAVITY = 9.80665

#: Ticks per second of the MTi's SampleTimeFine clock.
SAMPLE_TIME_FINE_HZ = 10_000


def earth_magnetic_field(inclination_deg: float = 67.0, north=(0.0, 0.0, 1.0), strength: float = 1.0) -> np.ndarray:
    """World (Y-up) magnetic field ``(3,)``: horizontal component towards ``north`` (a horizontal
    world direction), dipping ``inclination_deg`` below the horizon (67 deg: the Netherlands),
    magnitude ``strength`` (arbitrary units; Xsens normalises the local earth field to 1)."""
    n = np.asarray(north, dtype=np.float64)
    n = n - n[1] * np.array([0.0, 1.0, 0.0])
    if not np.linalg.norm(n) > 0:
        raise ValueError("north must have a horizontal component")
    n /= np.linalg.norm(n)
    inc = math.radians(inclination_deg)
    return strength * (math.cos(inc) * n + math.sin(inc) * np.array([0.0, -1.0, 0.0]))


@dataclass(frozen=True)
class ImuNoiseModel:
    """Noise and bias of one inertial sensor (per axis, sensor frame). See the module docstring for
    conventions and sources; all-zero fields give an ideal sensor."""

    #: Gyroscope white noise density, rad/s/sqrt(Hz) (MTi-1 datasheet: 0.007 deg/s/sqrt(Hz)).
    gyro_noise_density: float = math.radians(0.007)
    #: Accelerometer white noise density, m/s^2/sqrt(Hz) (MTi-1 datasheet: 120 ug/sqrt(Hz)).
    acc_noise_density: float = 120e-6 * STANDARD_GRAVITY
    #: Magnetometer white noise, a.u. per sample (assumption).
    mag_noise_sigma: float = 0.002
    #: Std of the constant gyroscope bias drawn per run, rad/s (assumption: 0.05 deg/s).
    gyro_bias_sigma: float = math.radians(0.05)
    #: Std of the constant accelerometer bias drawn per run, m/s^2 (assumption: ~0.5 mg).
    acc_bias_sigma: float = 0.005
    #: Gyroscope bias random walk, rad/s/sqrt(s) (0: constant bias).
    gyro_bias_walk: float = 0.0
    #: Accelerometer bias random walk, m/s^2/sqrt(s) (0: constant bias).
    acc_bias_walk: float = 0.0
    #: RMS angle of the orientation-output error, deg (MT0100P: static roll/pitch 0.5 deg).
    orientation_noise_deg: float = 0.5
    #: Correlation time of that error, s (~1 Hz fusion-filter crossover, MT0100P).
    orientation_noise_tau_s: float = 0.16
    #: Std of the constant heading (yaw about world +Y) offset per run, deg (MT0100P: 1.0 deg).
    heading_offset_deg: float = 1.0

    def __post_init__(self):
        for name, value in self.__dict__.items():
            if not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"ImuNoiseModel.{name} must be finite and non-negative, got {value}")

    @classmethod
    def ideal(cls) -> "ImuNoiseModel":
        """A sensor without noise, bias or orientation error."""
        return cls(**{k: 0.0 for k in cls.__dataclass_fields__})

    def white_sigma(self, density: float, rate_hz: float) -> float:
        """Per-sample std of white noise of ``density`` (unit/sqrt(Hz)) sampled at ``rate_hz``."""
        return density * math.sqrt(rate_hz / 2.0)


# --------------------------------------------------------------------------------------------
def specific_force(orientations, acceleration, gravity=GRAVITY) -> np.ndarray:
    """``R^T (a - g)`` ``(..., 3)``: what an accelerometer with orientation ``orientations (..., 4)``
    (xyzw, sensor-to-world) reads when its origin accelerates by ``acceleration (..., 3)`` (world,
    m/s^2). ``g`` is world gravity (default :data:`~dualhuman_builder.conventions.GRAVITY`)."""
    q = np.asarray(orientations, dtype=np.float64)
    f = np.asarray(acceleration, dtype=np.float64) - np.asarray(gravity, dtype=np.float64)
    batch = np.broadcast_shapes(q.shape[:-1], f.shape[:-1])
    q = np.array(np.broadcast_to(q, (*batch, 4))).reshape(-1, 4)
    f = np.array(np.broadcast_to(f, (*batch, 3))).reshape(-1, 3)
    return Rotation.from_quat(q).apply(f, inverse=True).reshape(*batch, 3)


@dataclass(frozen=True, eq=False)
class IdealImu:
    """Noise-free readings of ``N`` sensors at ``T`` times: ``orientation (T, N, 4)`` xyzw
    sensor-to-world; ``acc`` m/s^2, ``gyro`` rad/s, ``mag`` a.u., each ``(T, N, 3)`` in the sensor
    frame."""

    orientation: np.ndarray
    acc: np.ndarray
    gyro: np.ndarray
    mag: np.ndarray


def ideal_imu(kin: Kinematics, segments, mount_rotations=None, lever_arms=None,
              magnetic_field=None, gravity=GRAVITY) -> IdealImu:  # fmt: skip
    """Ideal readings of sensors on segment indices ``segments (N,)`` of ``kin``.

    ``mount_rotations (N, 4)`` xyzw: each sensor's frame in its segment's frame (default identity);
    ``lever_arms (N, 3)``: each sensor's origin in its segment's frame, m (default the segment
    origin); ``magnetic_field (3,)`` world field (default :func:`earth_magnetic_field`)."""
    segments = np.atleast_1d(np.asarray(segments, dtype=np.int64))
    N = segments.shape[0]
    mounts = np.tile([0.0, 0.0, 0.0, 1.0], (N, 1)) if mount_rotations is None else np.asarray(mount_rotations, float)
    arms = np.zeros((N, 3)) if lever_arms is None else np.asarray(lever_arms, dtype=np.float64)
    if mounts.shape != (N, 4) or arms.shape != (N, 3):
        raise ValueError(f"need mount_rotations (N, 4) and lever_arms (N, 3) for N = {N} sensors")
    field_w = earth_magnetic_field() if magnetic_field is None else np.asarray(magnetic_field, dtype=np.float64)
    T = kin.num_samples
    out = {k: np.empty((T, N, d)) for k, d in (("orientation", 4), ("acc", 3), ("gyro", 3), ("mag", 3))}
    for i, (s, q_m, r) in enumerate(zip(segments, mounts, arms)):
        m = Rotation.from_quat(q_m)
        r_ws = kin.rotations(int(s)) * m
        _, _, a = kin.point(int(s), r)
        out["orientation"][:, i] = r_ws.as_quat()
        out["acc"][:, i] = specific_force(out["orientation"][:, i], a, gravity)
        out["gyro"][:, i] = m.apply(np.array(kin.angular_velocity_body[:, s]), inverse=True)
        out["mag"][:, i] = r_ws.apply(np.tile(field_w, (T, 1)), inverse=True)
    return IdealImu(**out)


def gauss_markov(rng: np.random.Generator, n: int, shape: tuple, sigma: float, tau_s: float, dt_s: float) -> np.ndarray:
    """First-order Gauss-Markov (AR(1)) process ``(n, *shape)``, stationary std ``sigma`` from the
    first sample on, correlation ``exp(-lag / tau_s)``; ``tau_s = 0`` gives white noise."""
    w = rng.standard_normal((n, *shape))
    if sigma == 0 or n == 0:
        return np.zeros((n, *shape))
    if tau_s <= 0:
        return sigma * w
    a = math.exp(-dt_s / tau_s)
    b = math.sqrt(1.0 - a * a)
    x = np.empty_like(w)
    x[0] = w[0]
    if n > 1:
        x[1:], _ = lfilter([b], [1.0, -a], w[1:], axis=0, zi=(a * w[0])[None])
    return sigma * x


@dataclass(frozen=True, eq=False)
class ImuErrors:
    """The realised error processes of ``N`` sensors: ``gyro_bias``, ``acc_bias (T, N, 3)`` and the
    white noise added, ``gyro_noise``, ``acc_noise``, ``mag_noise (T, N, 3)``."""

    gyro_bias: np.ndarray
    acc_bias: np.ndarray
    gyro_noise: np.ndarray
    acc_noise: np.ndarray
    mag_noise: np.ndarray


def imu_errors(rng: np.random.Generator, T: int, N: int, rate_hz: float, noise: ImuNoiseModel) -> ImuErrors:
    """Draw biases (constant per run plus the optional random walk) and white noise for ``N``
    sensors over ``T`` samples at ``rate_hz``."""
    dt = 1.0 / rate_hz

    def bias(sigma, walk):
        b = rng.normal(0.0, 1.0, (1, N, 3)) * sigma
        steps = rng.normal(0.0, 1.0, (T, N, 3)) * (walk * math.sqrt(dt))
        steps[0] = 0.0
        return b + np.cumsum(steps, axis=0)

    gyro_bias = bias(noise.gyro_bias_sigma, noise.gyro_bias_walk)
    acc_bias = bias(noise.acc_bias_sigma, noise.acc_bias_walk)
    gyro_noise = rng.normal(0.0, 1.0, (T, N, 3)) * noise.white_sigma(noise.gyro_noise_density, rate_hz)
    acc_noise = rng.normal(0.0, 1.0, (T, N, 3)) * noise.white_sigma(noise.acc_noise_density, rate_hz)
    mag_noise = rng.normal(0.0, 1.0, (T, N, 3)) * noise.mag_noise_sigma
    return ImuErrors(gyro_bias, acc_bias, gyro_noise, acc_noise, mag_noise)


# --------------------------------------------------------------------------------------------
@dataclass(eq=False)
class ImuStream:
    """One MTi-style IMU's samples, plus the truth behind them.

    Reported (what :meth:`__iter__` yields as :class:`ImuSample`): ``counter (T,)`` u16 packet
    counter (wraps at 65536); ``device_time_ns (T,)`` SampleTimeFine ticks (10 kHz) as ns;
    ``host_time_ns (T,)``; ``orientation (T, 4)`` xyzw sensor-to-world with the orientation error;
    ``acceleration``, ``rate_of_turn``, ``magnetic_field (T, 3)`` in the sensor frame.

    Truth: ``true_time_ns (T,)`` the scene times of the samples; ``true_orientation (T, 4)``;
    ``ideal`` the noise-free readings; ``errors`` the realised biases and noise;
    ``orientation_error (T, 3)`` the rotation vector (sensor frame) of the fast orientation error;
    ``heading_offset_rad``; ``segment``, ``mount_rotation (4,)``, ``lever_arm (3,)``; ``clock``.
    """

    device: str
    segment: str
    rate_hz: float
    counter: np.ndarray
    device_time_ns: np.ndarray
    host_time_ns: np.ndarray
    orientation: np.ndarray
    acceleration: np.ndarray
    rate_of_turn: np.ndarray
    magnetic_field: np.ndarray
    true_time_ns: np.ndarray
    true_orientation: np.ndarray
    ideal: IdealImu
    errors: ImuErrors
    orientation_error: np.ndarray
    heading_offset_rad: float
    mount_rotation: np.ndarray
    lever_arm: np.ndarray
    clock: DeviceClock
    noise: ImuNoiseModel = field(default_factory=ImuNoiseModel)

    def __len__(self) -> int:
        return self.counter.shape[0]

    def __iter__(self) -> Iterator[ImuSample]:
        for k in range(len(self)):
            yield ImuSample(device=self.device, counter=int(self.counter[k]),
                            device_time_ns=int(self.device_time_ns[k]), host_time_ns=int(self.host_time_ns[k]),
                            orientation=self.orientation[k],
                            acceleration=self.acceleration[k], rate_of_turn=self.rate_of_turn[k],
                            magnetic_field=self.magnetic_field[k], status=0)  # fmt: skip


def freeze_arrays(obj) -> None:
    """Make every array attribute of ``obj`` (and of dataclasses it holds) read-only."""
    for v in vars(obj).values():
        if isinstance(v, np.ndarray):
            v.setflags(write=False)
        elif isinstance(v, (IdealImu, ImuErrors)):
            freeze_arrays(v)


def simulate_imu(gt: SkeletonTrack | KinematicSpline, segment: str, rate_hz: float = 400.0,
                 noise: ImuNoiseModel = ImuNoiseModel(), seed: int = 0, clock: DeviceClock = DeviceClock(),
                 device: str = "mti-0", mount_rotation=None, lever_arm=(0.0, 0.0, 0.0),
                 first_counter: int = 0, magnetic_field=None) -> ImuStream:  # fmt: skip
    """A single MTi-style IMU strapped to ``segment`` of the ground truth ``gt``.

    Samples at ``rate_hz`` on the device's own clock (``clock``: offset, drift, host stamping);
    ``rate_hz`` must divide the 10 kHz SampleTimeFine clock (400 and 100 Hz do). The packet counter
    starts at ``first_counter`` and wraps at 65536. ``mount_rotation (4,)`` xyzw and ``lever_arm
    (3,)`` m place the sensor in the segment frame. ``gt`` is never modified; pass a
    :class:`KinematicSpline` of it to reuse one fit for several devices.
    """
    step = SAMPLE_TIME_FINE_HZ / rate_hz
    if not (rate_hz > 0 and abs(step - round(step)) < 1e-9):
        raise ValueError(f"rate_hz must divide the {SAMPLE_TIME_FINE_HZ} Hz SampleTimeFine clock, got {rate_hz}")
    step = int(round(step))
    spline = as_spline(gt)
    seg = spline.track.segment_index(segment)
    tick_ns = 1_000_000_000 // SAMPLE_TIME_FINE_HZ
    tick0 = int(math.ceil(float(clock.device_time_ns(spline.t0_ns)) / tick_ns))
    d_end = float(clock.offset_s * 1e9 + clock.rate * spline.t1_ns)
    n = int(math.floor((d_end / tick_ns - tick0) / step + 1e-9)) + 1
    device_ns = (tick0 + step * np.arange(n, dtype=np.int64)) * tick_ns
    true_ns = np.clip(clock.true_time_ns(device_ns), spline.t0_ns, spline.t1_ns)

    rngs = [np.random.default_rng(s) for s in np.random.SeedSequence([seed, 0x1A2B]).spawn(4)]
    kin = spline.evaluate(true_ns)
    mount = np.array([0.0, 0.0, 0.0, 1.0]) if mount_rotation is None else np.asarray(mount_rotation, dtype=np.float64)
    arm = np.asarray(lever_arm, dtype=np.float64)
    ideal = ideal_imu(kin, [seg], mount[None], arm[None], magnetic_field)
    errors = imu_errors(rngs[0], n, 1, rate_hz, noise)

    sigma_axis = math.radians(noise.orientation_noise_deg) / math.sqrt(3.0)
    orient_err = gauss_markov(rngs[1], n, (3,), sigma_axis, noise.orientation_noise_tau_s, 1.0 / rate_hz)
    heading = float(rngs[2].normal(0.0, math.radians(noise.heading_offset_deg)))
    true_rot = Rotation.from_quat(ideal.orientation[:, 0])
    meas_rot = Rotation.from_rotvec([0.0, heading, 0.0]) * true_rot * Rotation.from_rotvec(orient_err)

    stream = ImuStream(
        device=device, segment=segment, rate_hz=float(rate_hz),
        counter=((int(first_counter) + np.arange(n)) % 65536).astype(np.int64),
        device_time_ns=device_ns, host_time_ns=clock.host_time_ns(true_ns, rngs[3]),
        orientation=meas_rot.as_quat(),
        acceleration=ideal.acc[:, 0] + errors.acc_bias[:, 0] + errors.acc_noise[:, 0],
        rate_of_turn=ideal.gyro[:, 0] + errors.gyro_bias[:, 0] + errors.gyro_noise[:, 0],
        magnetic_field=ideal.mag[:, 0] + errors.mag_noise[:, 0],
        true_time_ns=np.round(true_ns).astype(np.int64), true_orientation=ideal.orientation[:, 0],
        ideal=ideal, errors=errors, orientation_error=orient_err, heading_offset_rad=heading,
        mount_rotation=mount, lever_arm=arm, clock=clock, noise=noise,
    )  # fmt: skip
    freeze_arrays(stream)
    return stream

"""An Xsens-MVN-like inertial suit: from ground-truth segment kinematics to the stream a suit
sends (23 segment orientations and positions per sample, MVN message type 02), plus the raw
readings of its 17 inertial sensors.

Error model (:class:`SuitErrorModel`), for segment ``s`` at sample ``k``::

    R_meas = Ry(psi_k) . R_true . M_s . exp([n_{k,s}]x)        (orientations, world Y-up)
    p_meas(Pelvis) = p_true(Pelvis) + d_k                        (root position)
    p_meas(child)  = p_meas(parent) + R_meas(parent) o_child
    o_child        = R_true(parent)^T (p_true(child) - p_true(parent))   (true bone offset, parent frame)

* ``n`` — dynamic orientation error: a Gauss-Markov process per segment and axis (segment frame),
  RMS angle ``orientation_noise_deg``, correlation time ``orientation_noise_tau_s``;
* ``M_s`` — constant sensor-to-segment misalignment per segment (calibration error), RMS angle
  ``misalignment_deg``: I2S orientation errors propagate linearly into segment orientations
  (Miezal, Taetz & Bleser, "On Inertial Body Tracking in the Presence of Model Calibration
  Errors", Sensors 16(7):1132, 2016);
* ``psi`` — heading drift: yaw about world +Y of the whole body, a linear ramp at
  ``heading_drift_deg_per_min`` with a random sign per run;
* ``d`` — drift of the inertial root position, a random walk applied to the whole skeleton
  (horizontal ``root_drift_m_per_sqrt_min`` and vertical ``root_drift_vertical_m_per_sqrt_min``:
  the std of the drift after one minute, per axis);
* positions follow by forward kinematics through :data:`MVN_PARENTS` with the ground-truth bone
  offsets, so the skeleton stays connected and orientation errors move the limbs, as in MVN's
  biomechanical model.

Defaults and their sources:

* 1.0 deg RMS dynamic orientation error: a lone Xsens sensor's filter is specified at 0.5 deg
  static roll/pitch, 1.0 deg static heading and 2 deg RMS dynamic ("MTi and MTx User Manual",
  Xsens MT0100P, sec. 4.2); MVN's body model constrains segments further (Roetenberg, Luinge &
  Slycke, "Xsens MVN: Full 6DOF Human Motion Tracking Using Miniature Inertial Sensors", Xsens
  technical report, 2009). Correlation 0.16 s: the ~1 Hz crossover of
  Xsens' fusion filter at its default gain (MT0100P, "Filter Gain") — a filtered estimate errs at
  low frequency, not sample by sample.
* 1.0 deg/min heading drift: without a usable magnetic reference, "attitude and heading estimates
  will degrade slowly (typically a degree every minute)" (Xsens "MTi User Manual", MT0605P,
  orientation performance section); MVN's current engine is "immune to magnetic distortions"
  (Schepers, Giuberti & Bellusci, "Xsens MVN: Consistent Tracking of Human Motion Using Inertial
  Sensing", Xsens white paper, 2018), i.e. it does not hold heading to the magnetometer, so a slow
  heading drift of the whole body is what remains.
* 5 cm per sqrt(minute) horizontal root drift, 1 cm vertical: an assumption of ours. No public
  figure states MVN's in-place drift; Roetenberg et al. (2009) and Schepers et al. (2018) describe
  contact-aided position that bounds it, and Xsens warns that unaided double integration
  of acceleration is usable "for a period of time only, in the order of seconds" (Xsens knowledge
  base, "How do I calculate position from acceleration"). The vertical scale is smaller because
  MVN's foot-floor contacts hold height.
* 2.0 deg RMS misalignment: an assumption of ours (real values depend on the calibration pose and
  the strapping); Miezal et al. (2016) show such errors pass one-to-one into segment orientations.
* raw sensor noise: :class:`~dualhuman_builder.sim.imu.ImuNoiseModel` (MTi-1 class figures).

The 17 sensors of MVN (Roetenberg et al. 2009; Schepers et al. 2018, Fig. 1) are on
:data:`MVN_SENSOR_SEGMENTS`; the other six segments (L5, L3, T12, Neck, toes) are interpolated
by MVN and get orientation errors here but no raw samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.body.mapping import MVN_PARENTS, MVN_SEGMENTS
from dualhuman_builder.capture.samples import SuitFrame
from dualhuman_builder.sim.imu import (IdealImu, ImuErrors, ImuNoiseModel, freeze_arrays, gauss_markov, ideal_imu,
                                       imu_errors)  # fmt: skip
from dualhuman_builder.sim.kinematics import DeviceClock, Kinematics, KinematicSpline, as_spline
from dualhuman_builder.tracks import SkeletonTrack

#: The MVN segments that carry an inertial sensor (17), in MVN segment order.
MVN_SENSOR_SEGMENTS = (
    "Pelvis", "T8", "Head", "RightShoulder", "RightUpperArm", "RightForeArm", "RightHand",
    "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand", "RightUpperLeg", "RightLowerLeg",
    "RightFoot", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot",
)  # fmt: skip

#: Where each sensor sits on its segment: halfway to the named segment's origin, or a fixed offset
#: (segment frame: x forward, y left, z up at the T-pose; metres) for the sacrum, sternum, head
#: band and the backs of the hands.
SENSOR_SITES: dict[str, str | tuple[float, float, float]] = {
    "Pelvis": (-0.10, 0.0, 0.0), "T8": (0.10, 0.0, 0.0), "Head": (0.0, 0.0, 0.10),
    "RightShoulder": "RightUpperArm", "RightUpperArm": "RightForeArm", "RightForeArm": "RightHand",
    "RightHand": (0.0, -0.05, 0.02), "LeftShoulder": "LeftUpperArm", "LeftUpperArm": "LeftForeArm",
    "LeftForeArm": "LeftHand", "LeftHand": (0.0, 0.05, 0.02), "RightUpperLeg": "RightLowerLeg",
    "RightLowerLeg": "RightFoot", "RightFoot": "RightToe", "LeftUpperLeg": "LeftLowerLeg",
    "LeftLowerLeg": "LeftFoot", "LeftFoot": "LeftToe",
}  # fmt: skip


@dataclass(frozen=True)
class SuitErrorModel:
    """How a simulated suit's output departs from the truth; see the module docstring for the
    model and the sources of the defaults. All-zero angles and drifts reproduce the ground truth."""

    #: RMS angle of the dynamic orientation error per segment, deg (MT0100P: 2 deg RMS dynamic for a
    #: lone sensor; MVN's body model constrains segments further).
    orientation_noise_deg: float = 1.0
    #: Correlation time of the dynamic orientation error, s (~1 Hz filter crossover, MT0100P).
    orientation_noise_tau_s: float = 0.16
    #: Heading (yaw about world +Y) drift rate of the whole body, deg/min; the sign is drawn per run
    #: (MT0605P: "typically a degree every minute").
    heading_drift_deg_per_min: float = 1.0
    #: Horizontal random-walk drift of the root position: std per axis after 1 min, m (assumption:
    #: several cm per minute).
    root_drift_m_per_sqrt_min: float = 0.05
    #: Vertical random-walk drift of the root position: std after 1 min, m (floor contacts bound it).
    root_drift_vertical_m_per_sqrt_min: float = 0.01
    #: RMS angle of the constant sensor-to-segment misalignment per segment, deg (assumption; see
    #: Miezal et al. 2016).
    misalignment_deg: float = 2.0
    #: RMS angle of each sensor's mounting rotation on its segment, deg (straps are never square);
    #: raw samples are in the sensor frame. Geometry, not error: MVN's calibration absorbs it.
    sensor_mount_deg: float = 10.0
    #: Noise and bias of the 17 raw inertial sensors.
    imu: ImuNoiseModel = field(default_factory=ImuNoiseModel)

    def __post_init__(self):
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if name != "imu" and not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"SuitErrorModel.{name} must be finite and non-negative, got {value}")

    @classmethod
    def ideal(cls) -> "SuitErrorModel":
        """A suit that reports the ground truth exactly, with ideal sensors (mounts still rotated)."""
        zeros = {k: 0.0 for k in cls.__dataclass_fields__ if k not in ("imu", "sensor_mount_deg")}
        return cls(**zeros, imu=ImuNoiseModel.ideal())


def random_rotations(rng: np.random.Generator, n: int, rms_deg: float) -> Rotation:
    """``n`` rotations whose rotation vectors are isotropic Gaussian with RMS angle ``rms_deg``."""
    return Rotation.from_rotvec(rng.normal(0.0, math.radians(rms_deg) / math.sqrt(3.0), (n, 3)))


@dataclass(eq=False)
class SuitStream:
    """One actor's simulated suit stream and the truth behind it.

    Reported (``T`` samples, 23 segments in MVN order, :data:`MVN_SEGMENTS`): ``sample_counter (T,)``
    from 0; ``time_code_ms (T,)`` ms since the first sample on the suit clock; ``device_time_ns``
    and ``host_time_ns (T,)``; ``orientations (T, 23, 4)`` xyzw and ``positions (T, 23, 3)`` m,
    world frame. Raw sensors (17, :data:`MVN_SENSOR_SEGMENTS`): ``sensor_acc`` m/s^2,
    ``sensor_gyro`` rad/s, ``sensor_mag`` a.u., each ``(T, 17, 3)`` in the sensor frame.

    Truth: ``true_time_ns (T,)`` scene times of the samples; ``truth`` the ground-truth
    :class:`Kinematics` there (MVN order); realised errors ``misalignment (23, 4)``,
    ``orientation_noise (T, 23, 3)`` rotation vectors (segment frame), ``heading_drift_rad (T,)``
    and its signed ``heading_drift_rate_rad_s``, ``root_drift (T, 3)`` m; sensors'
    ``sensor_mount (17, 4)`` (sensor frame in segment frame), ``sensor_lever_arm (17, 3)`` m,
    ``sensor_ideal`` and ``sensor_errors``; the ``clock`` and ``errors`` model used.
    """

    character: int
    actor: str
    rate_hz: float
    segment_names: tuple[str, ...]
    sample_counter: np.ndarray
    time_code_ms: np.ndarray
    device_time_ns: np.ndarray
    host_time_ns: np.ndarray
    orientations: np.ndarray
    positions: np.ndarray
    sensor_segments: tuple[str, ...]
    sensor_acc: np.ndarray
    sensor_gyro: np.ndarray
    sensor_mag: np.ndarray
    true_time_ns: np.ndarray
    truth: Kinematics
    misalignment: np.ndarray
    orientation_noise: np.ndarray
    heading_drift_rad: np.ndarray
    heading_drift_rate_rad_s: float
    root_drift: np.ndarray
    sensor_mount: np.ndarray
    sensor_lever_arm: np.ndarray
    sensor_ideal: IdealImu
    sensor_errors: ImuErrors
    clock: DeviceClock
    errors: SuitErrorModel

    def __len__(self) -> int:
        return self.sample_counter.shape[0]

    def frame(self, k: int) -> SuitFrame:
        """Sample ``k`` as the typed :class:`SuitFrame` a decoder yields."""
        return SuitFrame(character=self.character, sample_counter=int(self.sample_counter[k]),
                         time_code_ms=int(self.time_code_ms[k]), device_time_ns=int(self.device_time_ns[k]),
                         host_time_ns=int(self.host_time_ns[k]), segment_names=self.segment_names,
                         orientations=self.orientations[k], positions=self.positions[k])  # fmt: skip

    def __iter__(self) -> Iterator[SuitFrame]:
        return (self.frame(k) for k in range(len(self)))

    def to_track(self) -> SkeletonTrack:
        """The reported stream as a :class:`SkeletonTrack` (device and host times kept)."""
        return SkeletonTrack(segment_names=self.segment_names, orientations=self.orientations, positions=self.positions,
                             device_time_ns=self.device_time_ns, host_time_ns=self.host_time_ns, actor=self.actor,
                             fps=self.rate_hz, meta={"source": "sim.suit", "character": self.character})  # fmt: skip


def _sensor_lever_arms(kin: Kinematics) -> np.ndarray:
    """``(17, 3)`` sensor origins in their segment frames (MVN-ordered ``kin``), from its first sample."""
    rot0 = Rotation.from_quat(kin.orientations[0])
    arms = np.empty((len(MVN_SENSOR_SEGMENTS), 3))
    for i, seg in enumerate(MVN_SENSOR_SEGMENTS):
        site = SENSOR_SITES[seg]
        s = MVN_SEGMENTS.index(seg)
        if isinstance(site, str):
            c = MVN_SEGMENTS.index(site)
            arms[i] = 0.5 * rot0[s].apply(kin.positions[0, c] - kin.positions[0, s], inverse=True)
        else:
            arms[i] = site
    return arms


def simulate_suit(gt: SkeletonTrack | KinematicSpline, character: int = 0, rate_hz: float = 240.0,
                  errors: SuitErrorModel = SuitErrorModel(), seed: int = 0,
                  clock: DeviceClock = DeviceClock()) -> SuitStream:  # fmt: skip
    """Simulate one actor's suit from ground truth ``gt`` (a :class:`SkeletonTrack` holding the 23
    MVN segments, in any order; or a :class:`KinematicSpline` of one, to reuse its fit).

    Samples at ``rate_hz`` on the suit clock ``clock`` (device time = offset + drift; host time =
    receive time with latency and jitter) over the whole track. ``seed`` and ``character`` seed
    every random process, each from its own stream, so two actors with one seed still differ and
    switching one error off leaves the others' realisations unchanged. ``gt`` is never modified.
    """
    spline = as_spline(gt)
    missing = [s for s in MVN_SEGMENTS if s not in spline.segment_names]
    if missing:
        raise ValueError(f"ground truth lacks MVN segments {missing}; a suit reports all 23")
    order = [spline.segment_names.index(s) for s in MVN_SEGMENTS]
    device_ns, true_ns = clock.sample_times(spline.t0_ns, spline.t1_ns, rate_hz)
    kin = spline.evaluate(true_ns).select(order)
    T, S = kin.num_samples, len(MVN_SEGMENTS)
    dt = 1.0 / rate_hz
    t_rel = (true_ns - true_ns[0]) * 1e-9
    rng = {name: np.random.default_rng(s) for name, s in zip(
        ("misalign", "noise", "heading", "root", "mount", "imu", "host"),
        np.random.SeedSequence([int(seed), int(character), 0x5017]).spawn(7))}  # fmt: skip

    # orientations
    misalign = random_rotations(rng["misalign"], S, errors.misalignment_deg)
    sigma_axis = math.radians(errors.orientation_noise_deg) / math.sqrt(3.0)
    noise = gauss_markov(rng["noise"], T, (S, 3), sigma_axis, errors.orientation_noise_tau_s, dt)
    sign = 1.0 if rng["heading"].random() < 0.5 else -1.0
    heading_rate = sign * math.radians(errors.heading_drift_deg_per_min) / 60.0
    psi = heading_rate * t_rel
    true_rot = Rotation.from_quat(kin.orientations.reshape(-1, 4))
    yaw = Rotation.from_rotvec(np.repeat(psi, S)[:, None] * np.array([0.0, 1.0, 0.0]))
    mis = Rotation.from_quat(np.tile(misalign.as_quat(), (T, 1)))
    meas_rot = yaw * true_rot * mis * Rotation.from_rotvec(noise.reshape(-1, 3))
    orientations = meas_rot.as_quat().reshape(T, S, 4)

    # positions: drifting root, then forward kinematics with the true bone offsets
    per_min = np.array([errors.root_drift_m_per_sqrt_min, errors.root_drift_vertical_m_per_sqrt_min,
                        errors.root_drift_m_per_sqrt_min]) / math.sqrt(60.0)  # fmt: skip
    steps = rng["root"].standard_normal((T, 3)) * per_min * np.sqrt(np.diff(t_rel, prepend=t_rel[0]))[:, None]
    root_drift = np.cumsum(steps, axis=0)
    positions = np.empty((T, S, 3))
    positions[:, 0] = kin.positions[:, 0] + root_drift
    true_r = true_rot.as_matrix().reshape(T, S, 3, 3)
    meas_r = meas_rot.as_matrix().reshape(T, S, 3, 3)
    for c, name in enumerate(MVN_SEGMENTS[1:], start=1):
        p = MVN_SEGMENTS.index(MVN_PARENTS[name])
        offset = np.einsum("tji,tj->ti", true_r[:, p], kin.positions[:, c] - kin.positions[:, p])
        positions[:, c] = positions[:, p] + np.einsum("tij,tj->ti", meas_r[:, p], offset)

    # raw sensors: the true motion, seen from each sensor's frame
    sensor_idx = [MVN_SEGMENTS.index(s) for s in MVN_SENSOR_SEGMENTS]
    mounts = random_rotations(rng["mount"], len(sensor_idx), errors.sensor_mount_deg).as_quat()
    arms = _sensor_lever_arms(kin)
    ideal = ideal_imu(kin, sensor_idx, mounts, arms)
    err = imu_errors(rng["imu"], T, len(sensor_idx), rate_hz, errors.imu)

    stream = SuitStream(
        character=int(character), actor=spline.track.actor, rate_hz=float(rate_hz), segment_names=MVN_SEGMENTS,
        sample_counter=np.arange(T, dtype=np.int64), time_code_ms=(device_ns - device_ns[0]) // 1_000_000,
        device_time_ns=device_ns, host_time_ns=clock.host_time_ns(true_ns, rng["host"]),
        orientations=orientations, positions=positions, sensor_segments=MVN_SENSOR_SEGMENTS,
        sensor_acc=ideal.acc + err.acc_bias + err.acc_noise, sensor_gyro=ideal.gyro + err.gyro_bias + err.gyro_noise,
        sensor_mag=ideal.mag + err.mag_noise, true_time_ns=kin.times_ns, truth=kin,
        misalignment=misalign.as_quat(), orientation_noise=noise, heading_drift_rad=psi,
        heading_drift_rate_rad_s=heading_rate, root_drift=root_drift, sensor_mount=mounts, sensor_lever_arm=arms,
        sensor_ideal=ideal, sensor_errors=err, clock=clock, errors=errors,
    )  # fmt: skip
    freeze_arrays(stream)
    return stream

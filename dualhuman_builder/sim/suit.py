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

Realistic errors (fields that default to off; :meth:`SuitErrorModel.realistic` draws them per take)::

    R_meas = Ry(psi_k + r_s t_k + m_{k,s}) . R_true . M_s . exp([n_{k,s} + e_{k,s} u_{k,s}]x)
    p_meas(Pelvis) = p_true(Pelvis) + d_k + R_meas(Pelvis) j_Pelvis
    p_meas(child)  = p_meas(parent) + R_meas(parent) o'_child
    o'_child       = o_child / |o_child| * (|o_child| + dL_child) + j_child     (the suit's own skeleton)

* ``dL`` — segment length error: MVN scales its biomechanical model from body dimensions measured
  with a tape (body height, arm span, hip and knee height, foot length...; Roetenberg et al. 2009;
  Xsens "MVN User Manual", body dimensions); each dimension's measurement error
  passes into the segment lengths scaled from it. One draw per segment, shared by the left and
  right segment (MVN takes one value per dimension for both sides), Gaussian with std
  ``segment_length_sigma_m``;
* ``j`` — joint-centre offset: the suit's joint centres are its model's, not anny's bone heads; a
  constant offset per joint in the parent frame, perpendicular to the bone (3-D for the root), RMS
  length ``joint_centre_offset_m``;
* ``e u`` — soft-tissue error: a unit Gauss-Markov process per segment and axis (correlation
  ``orientation_noise_tau_s``) times an envelope that grows with the segment's angular speed and
  acceleration (``0.5 + |w|/(1 rad/s) + |dw/dt|/(10 rad/s^2)``) and, on segments in contact
  with the partner (``contact`` of :func:`simulate_suit`), by ``1 + soft_tissue_contact_gain``;
  the envelope is normalised over the take so that the error's RMS over all segments and samples
  is ``soft_tissue_deg``;
* ``r_s`` — each segment's own heading drift rate, Gaussian with std
  ``heading_drift_segment_deg_per_min``, on top of the body's common ramp ``psi``;
* ``m`` — magnetic-disturbance episodes: Poisson arrivals at ``magnetic_episode_rate_per_min``,
  each lasting a log-uniform time in [``magnetic_episode_min_s``, ``magnetic_episode_max_s``], a
  raised-cosine heading error of peak ``magnetic_episode_peak_deg`` (random sign; each segment
  weighted uniformly in [0.5, 1]);
* dropouts: Poisson arrivals at ``dropout_rate_per_min``, each a log-uniform time in
  [``dropout_min_s``, ``dropout_max_s``] during which the suit's frames are missing (the sample
  counter skips them, as MVN's does);
* bursts: host receive times of the suit's frames grouped in bursts every
  ``host_burst_period_s`` (random phase): a frame is received at the first burst after its own
  receive time.

Ranges of :meth:`SuitErrorModel.realistic` and their sources (drawn once per take; "U" uniform,
"logU" log-uniform):

* dynamic orientation error, RMS over the body ``sqrt(orientation_noise_deg^2 + soft_tissue_deg^2)``
  ~ U(2, 5) deg: 2 deg RMS dynamic for one sensor (MT0100P, sec. 4.2); joint angles within ~5 deg
  RMS of optical capture for the dominant angles of walking (Schepers et al. 2018); the filter
  part ``orientation_noise_deg`` ~ U(1, 2) deg, the rest soft tissue. Soft tissue moves skin-borne
  sensors against the bone with the motion, most at the thigh (Leardini, Chiari, Della Croce &
  Cappozzo, "Human movement analysis using stereophotogrammetry Part 3. Soft tissue artifact
  assessment and compensation", Gait & Posture 21(2):212-225, 2005); its scaling with angular
  speed and acceleration is an assumption of ours;
* ``soft_tissue_contact_gain`` ~ U(0.5, 1.5) (1.5-2.5 times the error on a segment pressed by the
  partner): an assumption of ours (a pressed segment squeezes the tissue under its strap);
* ``orientation_noise_tau_s`` ~ U(0.1, 0.3) s: around the ~1 Hz crossover of Xsens' filter
  (MT0100P), an assumption of ours for the spread;
* ``heading_drift_deg_per_min`` ~ logU(0.5, 2) and ``heading_drift_segment_deg_per_min`` ~
  logU(0.5, 2): "typically a degree every minute" per sensor without a magnetic reference
  (MT0605P); the spread around it, and how much MVN's body model couples the segments, are
  assumptions of ours;
* magnetic episodes: ``magnetic_episode_rate_per_min`` ~ U(0.5, 2), 1-8 s each,
  ``magnetic_episode_peak_deg`` ~ U(2, 10): in a motion lab the field's heading varies with a
  std of 3 deg above 1 m and up to 29 deg at 5 cm above the floor (de Vries, Veeger, Baten & van
  der Helm, "Magnetic distortion in motion labs, implications for validating inertial magnetic
  sensors", Gait & Posture 29(4):535-541, 2009); rate and durations are assumptions of ours;
* ``root_drift_m_per_sqrt_min`` ~ logU(0.02, 0.10), vertical ~ logU(0.005, 0.02): "several cm
  per minute", no public figure (see above); an assumption of ours;
* ``misalignment_deg`` ~ U(1, 3): ~2 deg typical after an N-/T-pose calibration, an assumption
  of ours (Miezal et al. 2016 for its effect); ``sensor_mount_deg`` ~ U(5, 15) (geometry);
* ``segment_length_sigma_m`` ~ U(0.01, 0.02): tape-measured body dimensions, an assumption of
  ours (1-2 cm per dimension);
* ``joint_centre_offset_m`` ~ U(0.01, 0.03): joint centres predicted from body dimensions miss
  the true ones by 1.5 to more than 3 cm for the hip (Hara, McGinley, Briggs, Baker & Sangeux,
  "Predicting the location of the hip joint centres...", Scientific Reports 6:37707, 2016;
  Harrington's equations 12.3 +- 5.9 mm, Davis' 25.0 +- 6.7 mm against CT: Mantovani, Ng &
  Lamontagne, Gait & Posture 44:48-54, 2016); the same spread for the other joints is ours;
* dropouts: ``dropout_rate_per_min`` ~ U(0.5, 3), 0.1-1 s each: a wireless suit loses packets
  when out of range or through its streamer (a maintainer of an MVN client reports 30-50 %
  packet loss with MVN Analyze's Network Streamer before 2024, ``pysio-hermes-mvn`` README); rate
  and durations are assumptions of ours;
* ``host_burst_period_s`` ~ logU(0.01, 0.1): an assumption of ours; the upper end is a Wi-Fi
  client in power-save mode, which receives its buffered frames at each beacon (IEEE 802.11
  default beacon interval 100 TU = 102.4 ms);
* raw sensor noise stays at :class:`~dualhuman_builder.sim.imu.ImuNoiseModel`'s figures.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields, replace
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
    # --- realistic errors, off by default (see the module docstring for the model and the ranges)
    #: RMS over the take of the motion-dependent (soft-tissue) orientation error, deg.
    soft_tissue_deg: float = 0.0
    #: Extra soft-tissue error of a segment in contact with the partner: factor ``1 + gain``.
    soft_tissue_contact_gain: float = 0.0
    #: Std of each segment's own heading drift rate around the body's, deg/min.
    heading_drift_segment_deg_per_min: float = 0.0
    #: Std of each segment length's error (the suit's skeleton from measured dimensions), m.
    segment_length_sigma_m: float = 0.0
    #: RMS length of the offset of each suit joint centre from anny's bone head, m.
    joint_centre_offset_m: float = 0.0
    #: Magnetic-disturbance episodes per minute.
    magnetic_episode_rate_per_min: float = 0.0
    #: Peak heading error of one episode, deg.
    magnetic_episode_peak_deg: float = 0.0
    #: Shortest and longest episode, s (log-uniform in between).
    magnetic_episode_min_s: float = 1.0
    magnetic_episode_max_s: float = 8.0
    #: Suit dropouts (frames missing) per minute.
    dropout_rate_per_min: float = 0.0
    #: Shortest and longest dropout, s (log-uniform in between).
    dropout_min_s: float = 0.1
    dropout_max_s: float = 1.0
    #: Period of the bursts in which the host receives the suit's frames, s (0: no bursts).
    host_burst_period_s: float = 0.0

    def __post_init__(self):
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            if name != "imu" and not (value >= 0 and math.isfinite(value)):
                raise ValueError(f"SuitErrorModel.{name} must be finite and non-negative, got {value}")
        ranges = (("magnetic_episode", self.magnetic_episode_min_s, self.magnetic_episode_max_s,
                   self.magnetic_episode_rate_per_min),
                  ("dropout", self.dropout_min_s, self.dropout_max_s, self.dropout_rate_per_min))  # fmt: skip
        for what, lo, hi, rate in ranges:
            if rate > 0 and not 0 < lo <= hi:
                raise ValueError(f"SuitErrorModel.{what}_min_s/_max_s must satisfy 0 < min <= max, got {lo}, {hi}")

    @classmethod
    def ideal(cls) -> "SuitErrorModel":
        """A suit that reports the ground truth exactly, with ideal sensors (mounts still rotated)."""
        zeros = {k: 0.0 for k in cls.__dataclass_fields__ if k not in ("imu", "sensor_mount_deg")}
        return cls(**zeros, imu=ImuNoiseModel.ideal())

    @classmethod
    def realistic(cls, rng: np.random.Generator) -> "SuitErrorModel":
        """Every parameter drawn once (one take) within the ranges of the module docstring."""

        def log_uniform(lo: float, hi: float) -> float:
            return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))

        dynamic = float(rng.uniform(2.0, 5.0))  # body RMS of the whole dynamic error, deg
        filtered = float(rng.uniform(1.0, 2.0))
        return cls(orientation_noise_deg=filtered, orientation_noise_tau_s=float(rng.uniform(0.1, 0.3)),
                   soft_tissue_deg=math.sqrt(dynamic**2 - filtered**2),
                   soft_tissue_contact_gain=float(rng.uniform(0.5, 1.5)),
                   heading_drift_deg_per_min=log_uniform(0.5, 2.0),
                   heading_drift_segment_deg_per_min=log_uniform(0.5, 2.0),
                   root_drift_m_per_sqrt_min=log_uniform(0.02, 0.10),
                   root_drift_vertical_m_per_sqrt_min=log_uniform(0.005, 0.02),
                   misalignment_deg=float(rng.uniform(1.0, 3.0)), sensor_mount_deg=float(rng.uniform(5.0, 15.0)),
                   segment_length_sigma_m=float(rng.uniform(0.01, 0.02)),
                   joint_centre_offset_m=float(rng.uniform(0.01, 0.03)),
                   magnetic_episode_rate_per_min=float(rng.uniform(0.5, 2.0)),
                   magnetic_episode_peak_deg=float(rng.uniform(2.0, 10.0)),
                   dropout_rate_per_min=float(rng.uniform(0.5, 3.0)),
                   host_burst_period_s=log_uniform(0.01, 0.1))  # fmt: skip

    @property
    def realistic_errors_on(self) -> bool:
        """True when any of the errors that default to off is switched on."""
        return any(getattr(self, k) > 0 for k in _REALISTIC_SWITCHES)


#: The fields that switch the realistic errors on (each off at 0).
_REALISTIC_SWITCHES = ("soft_tissue_deg", "heading_drift_segment_deg_per_min", "segment_length_sigma_m",
                       "joint_centre_offset_m", "magnetic_episode_rate_per_min", "dropout_rate_per_min",
                       "host_burst_period_s")  # fmt: skip


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

    Realistic errors (see :class:`SuitErrorModel`): ``segment_heading_rad (T, 23)`` the heading
    error of each segment (common ramp, own drift, magnetic episodes); ``segment_heading_rate_rad_s
    (23,)`` each segment's own drift rate; ``magnetic_heading_rad`` and ``soft_tissue`` (rotation
    vectors, segment frame, part of ``orientation_noise``) ``(T, 23)`` / ``(T, 23, 3)`` or None when
    off; ``segment_length_error_m (23,)`` the suit's length of the bone from each segment's parent
    to it minus the truth (0 for the pelvis); ``joint_centre_offset (23, 3)`` m, the suit's joint
    centre minus anny's, in the parent frame (the pelvis': in its own frame);
    ``dropout_start_ns``/``dropout_stop_ns (E,)`` scene times of the dropouts (stop exclusive):
    the samples inside are missing from every per-sample array, and ``sample_counter`` skips them.
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
    segment_heading_rad: np.ndarray | None = None
    segment_heading_rate_rad_s: np.ndarray | None = None
    magnetic_heading_rad: np.ndarray | None = None
    soft_tissue: np.ndarray | None = None
    segment_length_error_m: np.ndarray | None = None
    joint_centre_offset: np.ndarray | None = None
    dropout_start_ns: np.ndarray | None = None
    dropout_stop_ns: np.ndarray | None = None

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


def _poisson_events(rng: np.random.Generator, span_s: float, rate_per_min: float, lo_s: float,
                    hi_s: float) -> list[tuple[float, float]]:  # fmt: skip
    """``[(start_s, stop_s), ...]`` from 0: Poisson arrivals at ``rate_per_min`` (outside earlier
    events), each lasting a log-uniform time in ``[lo_s, hi_s]``."""
    events, t = [], 0.0
    if rate_per_min <= 0:
        return events
    while True:
        t += rng.exponential(60.0 / rate_per_min)
        if t >= span_s:
            return events
        stop = t + math.exp(rng.uniform(math.log(lo_s), math.log(hi_s)))
        events.append((t, stop))
        t = stop


def _suit_skeleton(rng: np.random.Generator, kin: Kinematics, errors: SuitErrorModel) -> tuple[np.ndarray, np.ndarray]:
    """The suit's own skeleton against the truth's: ``(length_error (23,), joint_offset (23, 3))``
    (see :class:`SuitStream`). Left and right segments share their length error."""
    S = len(MVN_SEGMENTS)
    by_side: dict[str, float] = {}
    length = np.zeros(S)
    offset = np.zeros((S, 3))
    r0 = Rotation.from_quat(kin.orientations[0])
    for c, name in enumerate(MVN_SEGMENTS):
        key = name.replace("Left", "").replace("Right", "")
        if c and key not in by_side:
            by_side[key] = float(rng.normal(0.0, errors.segment_length_sigma_m))
        j = rng.normal(0.0, errors.joint_centre_offset_m / math.sqrt(3.0 if c == 0 else 2.0), 3)
        if c:
            length[c] = by_side[key]
            p = MVN_SEGMENTS.index(MVN_PARENTS[name])
            bone = r0[p].apply(kin.positions[0, c] - kin.positions[0, p], inverse=True)
            u = bone / max(np.linalg.norm(bone), 1e-9)
            j -= u * (j @ u)  # perpendicular to the bone: the length error is dL alone
        offset[c] = j
    return length, offset


def _soft_tissue_envelope(kin: Kinematics, load: np.ndarray | None, gain: float) -> np.ndarray:
    """``(T, 23)`` envelope of the soft-tissue error, RMS 1 over the take (module docstring)."""
    w = np.linalg.norm(kin.angular_velocity_body, axis=-1)
    dw = np.linalg.norm(kin.angular_acceleration_body, axis=-1)
    env = 0.5 + w / 1.0 + dw / 10.0
    if load is not None:
        env = env * (1.0 + gain * load)
    rms = math.sqrt(float(np.mean(env**2))) if env.size else 1.0
    return env / rms if rms > 0 else np.ones_like(env)


def _bursts(host_ns: np.ndarray, period_s: float, rng: np.random.Generator) -> np.ndarray:
    """Receive times ``host_ns`` moved to the first burst at or after them (period ``period_s``)."""
    period = period_s * 1e9
    phase = float(rng.uniform(0.0, period))
    k = np.ceil((host_ns.astype(np.float64) - phase) / period)
    return np.maximum(np.round(phase + k * period).astype(np.int64), host_ns)


#: The per-sample arrays of a :class:`SuitStream` (first axis: samples).
_PER_SAMPLE = ("sample_counter", "time_code_ms", "device_time_ns", "host_time_ns", "orientations", "positions",
               "sensor_acc", "sensor_gyro", "sensor_mag", "true_time_ns", "orientation_noise", "heading_drift_rad",
               "root_drift", "segment_heading_rad", "magnetic_heading_rad", "soft_tissue")  # fmt: skip


def _take(obj, keep: np.ndarray, names=None):
    """A copy of dataclass ``obj`` with its arrays ``names`` (default: all) cut to samples ``keep``."""
    names = names or [f.name for f in fields(obj)]
    return replace(obj, **{n: getattr(obj, n)[keep] for n in names if isinstance(getattr(obj, n), np.ndarray)})


def segment_loads(contact: np.ndarray, model=None, mapping=None, threshold: float | None = None) -> np.ndarray:
    """Which MVN segments of a body touch the partner: ``(F, 23)`` float 0/1 in MVN order, from
    one actor's per-vertex ``contact (F, V)``: bool labels, or signed distances to the partner (m,
    NaN far; :attr:`~dualhuman_builder.sim.scenes.Scene.distances`), a vertex touching below
    ``threshold`` (default the scenes' contact threshold). A vertex belongs to the segment of its
    strongest skinning bone, or of that bone's nearest ancestor that a segment maps to. Frames are
    read in chunks, so a long take's distances are never converted whole."""
    from dualhuman_builder.body.mapping import load_segment_mapping

    if model is None:
        from dualhuman_builder.body.model import get_body_model

        model = get_body_model()
    mapping = mapping or load_segment_mapping()
    seg_of_bone = {model.bone_index(mapping.bone_of(s)): i for i, s in enumerate(MVN_SEGMENTS)}
    bone_seg = np.zeros(len(model.bone_names), dtype=np.int64)
    for b in range(len(model.bone_names)):
        a = b
        while a >= 0 and a not in seg_of_bone:
            a = int(model.bone_parents[a])
        bone_seg[b] = seg_of_bone.get(a, 0)
    vert_seg = bone_seg[model.vertex_bone()]
    if threshold is None:
        from dualhuman_builder.sim.scenes import CONTACT_THRESHOLD as threshold
    out = np.zeros((contact.shape[0], len(MVN_SEGMENTS)))
    for a in range(0, contact.shape[0], 256):
        chunk = np.asarray(contact[a : a + 256])
        if chunk.dtype != bool:
            chunk = np.nan_to_num(chunk.astype(np.float32), nan=np.inf) < threshold
        for s in range(len(MVN_SEGMENTS)):
            cols = vert_seg == s
            if cols.any():
                out[a : a + 256, s] = chunk[:, cols].any(axis=1)
    return out


def simulate_suit(gt: SkeletonTrack | KinematicSpline, character: int = 0, rate_hz: float = 240.0,
                  errors: SuitErrorModel = SuitErrorModel(), seed: int = 0,
                  clock: DeviceClock = DeviceClock(), contact: np.ndarray | None = None) -> SuitStream:  # fmt: skip
    """Simulate one actor's suit from ground truth ``gt`` (a :class:`SkeletonTrack` holding the 23
    MVN segments, in any order; or a :class:`KinematicSpline` of one, to reuse its fit).

    Samples at ``rate_hz`` on the suit clock ``clock`` (device time = offset + drift; host time =
    receive time with latency and jitter) over the whole track. ``seed`` and ``character`` seed
    every random process, each from its own stream, so two actors with one seed still differ and
    switching one error off leaves the others' realisations unchanged. ``gt`` is never modified.
    ``contact``: optional ``(F, 23)`` load in [0, 1] of each MVN segment (MVN order) at the track's
    ``F`` frames (:func:`segment_loads`); it raises the soft-tissue error of pressed segments.
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
    # the realistic errors' own streams: switching them on leaves the ideal realisations unchanged
    more = {name: np.random.default_rng(s) for name, s in zip(
        ("skeleton", "tissue", "segment_heading", "magnetic", "dropout", "burst"),
        np.random.SeedSequence([int(seed), int(character), 0x5018]).spawn(6))}  # fmt: skip

    # orientations
    misalign = random_rotations(rng["misalign"], S, errors.misalignment_deg)
    sigma_axis = math.radians(errors.orientation_noise_deg) / math.sqrt(3.0)
    noise = gauss_markov(rng["noise"], T, (S, 3), sigma_axis, errors.orientation_noise_tau_s, dt)
    tissue = None
    if errors.soft_tissue_deg > 0:
        load = None
        if contact is not None and errors.soft_tissue_contact_gain > 0:
            contact = np.asarray(contact, dtype=np.float64)
            if contact.shape != (spline.track.num_frames, S):
                raise ValueError(f"contact must be (frames, 23) = {(spline.track.num_frames, S)}, got {contact.shape}")
            frame_ns = spline.track.device_time_ns
            load = np.stack([np.interp(true_ns, frame_ns, contact[:, k]) for k in range(S)], axis=1)
        env = _soft_tissue_envelope(kin, load, errors.soft_tissue_contact_gain)
        tissue = gauss_markov(more["tissue"], T, (S, 3), math.radians(errors.soft_tissue_deg) / math.sqrt(3.0),
                              errors.orientation_noise_tau_s, dt) * env[..., None]  # fmt: skip
        noise = noise + tissue
    sign = 1.0 if rng["heading"].random() < 0.5 else -1.0
    heading_rate = sign * math.radians(errors.heading_drift_deg_per_min) / 60.0
    psi = heading_rate * t_rel
    true_rot = Rotation.from_quat(kin.orientations.reshape(-1, 4))
    seg_rate = more["segment_heading"].normal(0.0, math.radians(errors.heading_drift_segment_deg_per_min) / 60.0, S)
    magnetic = None
    if errors.magnetic_episode_rate_per_min > 0 and errors.magnetic_episode_peak_deg > 0:
        magnetic = np.zeros((T, S))
        r = more["magnetic"]
        for a, b in _poisson_events(r, float(t_rel[-1]) if T else 0.0, errors.magnetic_episode_rate_per_min,
                                    errors.magnetic_episode_min_s, errors.magnetic_episode_max_s):  # fmt: skip
            peak = math.radians(errors.magnetic_episode_peak_deg) * (1.0 if r.random() < 0.5 else -1.0)
            weight = r.uniform(0.5, 1.0, S)
            inside = (t_rel >= a) & (t_rel < b)
            bump = 0.5 - 0.5 * np.cos(2.0 * np.pi * (t_rel[inside] - a) / (b - a))
            magnetic[inside] += peak * bump[:, None] * weight[None, :]
    seg_psi = psi[:, None] + seg_rate[None, :] * t_rel[:, None] + (0.0 if magnetic is None else magnetic)
    if errors.heading_drift_segment_deg_per_min > 0 or magnetic is not None:
        yaw = Rotation.from_rotvec(seg_psi.reshape(-1)[:, None] * np.array([0.0, 1.0, 0.0]))
    else:
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
    own_skeleton = errors.segment_length_sigma_m > 0 or errors.joint_centre_offset_m > 0
    length_err, joint_off = (_suit_skeleton(more["skeleton"], kin, errors) if own_skeleton and T
                             else (np.zeros(S), np.zeros((S, 3))))  # fmt: skip
    if own_skeleton:
        positions[:, 0] += np.einsum("tij,j->ti", meas_r[:, 0], joint_off[0])
    for c, name in enumerate(MVN_SEGMENTS[1:], start=1):
        p = MVN_SEGMENTS.index(MVN_PARENTS[name])
        offset = np.einsum("tji,tj->ti", true_r[:, p], kin.positions[:, c] - kin.positions[:, p])
        if own_skeleton:
            norm = np.linalg.norm(offset, axis=-1, keepdims=True)
            offset = offset / np.maximum(norm, 1e-9) * np.maximum(norm + length_err[c], 0.3 * norm) + joint_off[c]
        positions[:, c] = positions[:, p] + np.einsum("tij,tj->ti", meas_r[:, p], offset)

    # raw sensors: the true motion, seen from each sensor's frame
    sensor_idx = [MVN_SEGMENTS.index(s) for s in MVN_SENSOR_SEGMENTS]
    mounts = random_rotations(rng["mount"], len(sensor_idx), errors.sensor_mount_deg).as_quat()
    arms = _sensor_lever_arms(kin)
    ideal = ideal_imu(kin, sensor_idx, mounts, arms)
    err = imu_errors(rng["imu"], T, len(sensor_idx), rate_hz, errors.imu)
    host_ns = clock.host_time_ns(true_ns, rng["host"])
    if errors.host_burst_period_s > 0:
        host_ns = _bursts(host_ns, errors.host_burst_period_s, more["burst"])

    stream = SuitStream(
        character=int(character), actor=spline.track.actor, rate_hz=float(rate_hz), segment_names=MVN_SEGMENTS,
        sample_counter=np.arange(T, dtype=np.int64), time_code_ms=(device_ns - device_ns[0]) // 1_000_000,
        device_time_ns=device_ns, host_time_ns=host_ns,
        orientations=orientations, positions=positions, sensor_segments=MVN_SENSOR_SEGMENTS,
        sensor_acc=ideal.acc + err.acc_bias + err.acc_noise, sensor_gyro=ideal.gyro + err.gyro_bias + err.gyro_noise,
        sensor_mag=ideal.mag + err.mag_noise, true_time_ns=kin.times_ns, truth=kin,
        misalignment=misalign.as_quat(), orientation_noise=noise, heading_drift_rad=psi,
        heading_drift_rate_rad_s=heading_rate, root_drift=root_drift, sensor_mount=mounts, sensor_lever_arm=arms,
        sensor_ideal=ideal, sensor_errors=err, clock=clock, errors=errors, segment_heading_rad=seg_psi,
        segment_heading_rate_rad_s=seg_rate, magnetic_heading_rad=magnetic, soft_tissue=tissue,
        segment_length_error_m=length_err, joint_centre_offset=joint_off,
        dropout_start_ns=np.zeros(0, dtype=np.int64), dropout_stop_ns=np.zeros(0, dtype=np.int64),
    )  # fmt: skip
    if errors.dropout_rate_per_min > 0 and T:
        events = _poisson_events(more["dropout"], float(t_rel[-1]), errors.dropout_rate_per_min, errors.dropout_min_s,
                                 errors.dropout_max_s)  # fmt: skip
        keep = np.ones(T, dtype=bool)
        for a, b in events:
            keep &= ~((t_rel >= a) & (t_rel < b))
        t0 = float(true_ns[0])
        starts = np.array([round(t0 + a * 1e9) for a, _ in events], dtype=np.int64)
        stops = np.array([round(t0 + b * 1e9) for _, b in events], dtype=np.int64)
        stream = _take(stream, keep, _PER_SAMPLE)
        stream.truth = _take(kin, keep)
        stream.sensor_ideal, stream.sensor_errors = _take(ideal, keep), _take(err, keep)
        stream.dropout_start_ns, stream.dropout_stop_ns = starts, stops
    freeze_arrays(stream)
    return stream

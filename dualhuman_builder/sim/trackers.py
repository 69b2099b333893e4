"""HTC-VIVE-like trackers strapped to body segments: ~250 Hz world poses with millimetre noise,
mounting offsets, occasional tracking loss, and a clock of their own.

Model (:class:`TrackerErrorModel`), for a tracker on segment ``s`` with mounting rotation ``M`` and
translation ``m`` (the tracker's frame and origin in the segment frame, drawn per run around a
nominal site on the body surface, :data:`~dualhuman_builder.rig.TRACKER_SITES`):

* true pose ``R_tr = R_seg M``, ``p_tr = p_seg + R_seg m`` (world, Y-up), with its velocity and
  angular velocity (world frame) from the ground-truth splines;
* reported pose: ``p_tr + n_p`` (white, per axis) and ``R_tr exp([n_r]x)`` (white, RMS angle);
  velocities with white noise too;
* tracking loss: events arrive as a Poisson process at ``loss_rate_per_min`` per minute of tracked
  time, each lasting a log-uniform time in ``loss_duration_s``. A loss is reported, as real trackers
  do through OpenVR (``TriadSemi/triad_openvr`` issue 16), either as ``valid=False`` with the last pose held,
  or — a fraction ``loss_origin_fraction`` of events — as a jump of the pose to the origin
  (position 0, identity orientation, zero velocities) with ``valid`` still True;
* clock: all trackers of one lighthouse system share a :class:`DeviceClock` that differs from the
  suit's by a constant offset and a linear drift (ppm); each tracker's samples are stamped by the
  host on receipt with their own latency jitter.

Defaults (the ``ideal`` preset) and their sources:

* 1 mm position noise per axis, 0.3 deg RMS orientation noise: Niehorster, Li & Lappe, "The
  Accuracy and Precision of Position and Orientation Tracking in the HTC Vive Virtual Reality
  System for Scientific Research", i-Perception 8(3), 2017, find the Vive's precision high and
  its latency 22 ms; Bauer,
  Lienhart & Jost, Sensors 21(5):1622, 2021, find position readings reproducible within a few
  millimetres but systematic effects of centimetres and a 0.4 deg tilt of the reference frame;
  Sansone et al., Virtual Reality (2021), doi:10.1007/s10055-021-00584-5, give a static
  accuracy of 0.5 +- 0.2 cm horizontally; Merker et al., Sensors 23(17):7371, 2023, compare VIVE
  Tracker 3.0 with Vicon on a moving body. 1 mm white noise is our choice for a strapped, moving
  tracker; the sub-degree orientation noise our reading of the same studies. The ideal preset
  leaves the biases below off.
* loss: 2 events per minute lasting 20-400 ms: assumptions for two people in close contact
  occluding each other.
* clock: 30 ppm drift, a typical crystal tolerance (the Awinda station, the suit's clock, is
  specified by Xsens at <= 1 ppm), and an arbitrary 0.25 s offset — OpenVR exposes no
  device time (openvr #1007); libsurvive's tracker timecode counts from power-on.
* velocity noise 0.01 m/s and angular-velocity noise 0.02 rad/s: assumptions (OpenVR's velocities
  are filter outputs).

Realistic errors (fields that default to off; :meth:`TrackerErrorModel.realistic` draws them per
take within :data:`REALISTIC_RANGES`). The reported position is ::

    p_rep = T (p_tr' + d(p_tr')) + g_k + o_a + j_k + n_p        p_tr' = p_seg + R_seg (m + u_k)
    R_rep = T R_tr exp([n_r]x)

* ``g`` — correlated dynamic error: a first-order Gauss-Markov process per tracker and axis, 3-D
  RMS ``correlated_error_m`` (horizontal and vertical stds in the ratio 1 : ``vertical_ratio``),
  correlation time ``correlated_error_tau_s``. Range 5-10 mm: Merker et al. (2023) measure
  10.4 +- 4.5 mm (knee) and 11.3 +- 5.1 mm (ankle) against Vicon on a moving body, Sansone et al.
  (2021) 5 +- 2 mm horizontally and 17 +- 12 mm vertically static (vertical to horizontal ratio
  1-3 drawn: the static 3.4 includes their per-acquisition offset, below). The correlation
  time, 0.3-3 s, is an assumption: no study reports one; lighthouse solutions err with the pose
  against the stations, which changes as fast as a body moves.
* ``o_a`` — offset per acquisition: constant while tracked, drawn anew at the start and after every
  loss (re-acquisition), 3-D RMS ``acquisition_offset_m`` with the same vertical ratio. Range
  5-15 mm: Sansone et al. (2021) find "every acquisition was characterised by an initial random
  offset" (vertical spread +- 12 mm); Niehorster et al. (2017) find "large changes in offset
  whenever tracking was briefly lost".
* ``T`` and ``d`` — systematic distortion of the tracking space: ``T`` a tilt of the reference frame
  by ``frame_tilt_deg`` about a horizontal axis through the world origin (azimuth
  ``frame_tilt_azimuth_deg`` from +X towards +Z), so height errors grow with horizontal distance;
  ``d`` a smooth displacement field, a sum of :data:`FIELD_MODES` plane waves per axis with random
  directions and phases (seeded by ``field_seed``), wavelength ``field_wavelength_m``, RMS
  ``field_distortion_m`` per axis. Ranges: tilt 0.2-0.6 deg around Bauer et al.'s (2021) 0.4 deg
  (Niehorster et al. and Sansone et al. also find the frame tilted); field RMS 5-15 mm per axis at
  4-10 m wavelength, so that a room-sized volume sees "systematic effects with magnitudes of several
  centimetres" (Bauer et al. 2021) while points a body apart differ by millimetres (our reading:
  Merker et al.'s 10-11 mm on a moving body leave little room for more).
* occlusion by the partner: with ``stations`` (lighthouse base station positions, world, m) and the
  partner's kinematics (``occluder`` of :func:`simulate_trackers`), a tracker is hidden while every
  station's line of sight to it passes through the partner's body, approximated by capsules
  between the partner's segment origins (:data:`OCCLUDER_CAPSULES`, radii from adult
  circumferences: torso 13 cm, upper arm 5 cm...); a tracker inside a capsule (pressed against the
  partner) counts as hidden. Hidden spells shorter than :data:`IMU_BRIDGE_S` are bridged by the
  tracker's IMU; longer ones are losses (``valid=False``, last pose held, as OpenVR reports them)
  that last until ``reacquire_delay_s`` after the tracker is seen again. Stations: two at opposite
  corners of a square room, half-size 1.5-2.5 m, 2.2-2.8 m high ("above head height", HTC's
  base-station setup guide), the diagonal at a random azimuth. Delay 0.1-0.5 s: an assumption (a
  lighthouse solver needs several sweeps to lock on again). Self-occlusion and the trackers'
  facing are not modelled: whether a wrist behind the partner's back is lost depends on where the
  stations are. Re-acquisition delay and offset are the same for random and occlusion losses.
* ``j`` — jumps: Poisson events at ``jump_rate_per_min``, each displacing the position by a random
  direction times a log-uniform length in ``jump_size_m`` for a log-uniform time in
  ``jump_duration_s``, ``valid`` still True. Assumptions: 0.5-3 per minute, 1-5 cm, 10-200 ms;
  reflections and ambiguous solutions with several stations (Bauer et al. 2021: "the tracking
  algorithm faces problems when several lighthouses are used"; openvr #1150: trackers that keep
  moving while occluded).
* ``u`` — strap slip under contact: the mount (segment frame) shifts by a random step, per axis
  std ``strap_slip_m``, at the start of every contact episode and stays there (a strap does not
  slide back), ramping over :data:`SLIP_RAMP_S`, its norm capped at :data:`SLIP_MAX_M`. Contact is
  not known to the tracker simulator; it is taken as the partner's body (the occluder capsules'
  surface) within ``slip_contact_m`` of the tracker's centre, leaving at twice that distance.
  Ranges: steps of 2-10 mm per axis (assumption: straps over clothing move by millimetres to a
  centimetre when pressed or pulled); contact within 5-10 cm (the tracker stands ~4 cm off the
  skin, and the capsules err by centimetres against a real body).
* realistic jitter 0.3-1 mm, orientation noise 0.2-0.5 deg, mount spread 5-20 mm and 5-15 deg,
  random (RF) losses 0-1 per minute of 20-400 ms with 0-20 % of them jumps to the origin, velocity
  noise 0.01-0.03 m/s and 0.02-0.05 rad/s: the defaults' sources widened into ranges
  (assumptions).
* :func:`realistic_tracker_clock`: latency 15-30 ms around Niehorster et al.'s 22 ms, exponential
  jitter of mean 1-4 ms (assumption: OpenVR poses are polled on the host's frame loop), offset
  0-10 s (arbitrary: no device time is exposed) and drift -50..+50 ppm (common crystal
  tolerances; assumption).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.samples import TrackerSample
from dualhuman_builder.sim.imu import freeze_arrays, gauss_markov
from dualhuman_builder.sim.kinematics import DeviceClock, KinematicSpline, as_spline
from dualhuman_builder.sim.suit import random_rotations
from dualhuman_builder.rig import tracker_site
from dualhuman_builder.tracks import SkeletonTrack

#: Default tracker sites per actor: serial suffix -> MVN segment (the capture protocol's pelvis,
#: head, wrists and ankles: the hand and foot segment origins are the wrist and ankle joints).
DEFAULT_SITES = {"PELVIS": "Pelvis", "HEAD": "Head", "LHAND": "LeftHand", "RHAND": "RightHand",
                 "LFOOT": "LeftFoot", "RFOOT": "RightFoot"}  # fmt: skip

#: The tracker system's default clock against the scene (and the default suit) clock.
DEFAULT_TRACKER_CLOCK = DeviceClock(offset_s=0.25, drift_ppm=30.0, latency_s=0.004, jitter_s=0.001)


def default_sites(prefix: str = "SIM") -> dict[str, str]:
    """``{prefix-PELVIS: "Pelvis", prefix-HEAD: "Head", ...}``: six trackers of one actor, named as
    in ``rigs/sim.toml`` (prefix ``SIM-A`` gives ``SIM-A-LHAND``, ...)."""
    return {f"{prefix}-{suffix}": segment for suffix, segment in DEFAULT_SITES.items()}


#: Realistic parameter ranges ``field -> (low, high)`` that :meth:`TrackerErrorModel.realistic` draws from
#: (uniformly; the module docstring gives the source of each).
REALISTIC_RANGES: dict[str, tuple[float, float]] = {
    "position_noise_m": (0.0003, 0.001), "orientation_noise_deg": (0.2, 0.5),
    "velocity_noise_m_s": (0.01, 0.03), "angular_velocity_noise_rad_s": (0.02, 0.05),
    "mount_translation_sigma_m": (0.005, 0.02), "mount_rotation_deg": (5.0, 15.0),
    "loss_rate_per_min": (0.0, 1.0), "loss_origin_fraction": (0.0, 0.2),
    "correlated_error_m": (0.005, 0.010), "correlated_error_tau_s": (0.3, 3.0), "vertical_ratio": (1.0, 3.0),
    "acquisition_offset_m": (0.005, 0.015),
    "frame_tilt_deg": (0.2, 0.6), "frame_tilt_azimuth_deg": (0.0, 360.0),
    "field_distortion_m": (0.005, 0.015), "field_wavelength_m": (4.0, 10.0),
    "reacquire_delay_s": (0.1, 0.5), "jump_rate_per_min": (0.5, 3.0),
    "strap_slip_m": (0.002, 0.01), "slip_contact_m": (0.05, 0.10),
    "station_half_size_m": (1.5, 2.5), "station_height_m": (2.2, 2.8), "station_azimuth_deg": (0.0, 180.0),
}  # fmt: skip

#: Plane waves per axis in the displacement field ``d``.
FIELD_MODES = 4
#: Hidden spells shorter than this (s) are bridged by the tracker's IMU and are not losses (assumption).
IMU_BRIDGE_S = 0.05
#: Time (s) over which one strap slip step takes effect, and the largest total slip (m); assumptions.
SLIP_RAMP_S = 0.2
SLIP_MAX_M = 0.03

#: The partner's body as capsules ``(from segment, to segment, radius m)`` between MVN segment origins;
#: ``(segment, None, radius)`` extends the segment beyond its origin (head and hands, see
#: :data:`CAPSULE_EXTENSIONS`). Radii from adult circumferences (waist ~85 cm around a 30 x 20 cm section,
#: upper arm ~30 cm, forearm ~25 cm, thigh ~55 cm, calf ~37 cm), rounded.
OCCLUDER_CAPSULES = (
    ("Pelvis", "L5", 0.14), ("L5", "L3", 0.13), ("L3", "T12", 0.13), ("T12", "T8", 0.13), ("T8", "Neck", 0.11),
    ("Neck", "Head", 0.06), ("Head", None, 0.10),
    ("T8", "RightUpperArm", 0.08), ("RightUpperArm", "RightForeArm", 0.05), ("RightForeArm", "RightHand", 0.04),
    ("RightHand", None, 0.045),
    ("T8", "LeftUpperArm", 0.08), ("LeftUpperArm", "LeftForeArm", 0.05), ("LeftForeArm", "LeftHand", 0.04),
    ("LeftHand", None, 0.045),
    ("Pelvis", "RightUpperLeg", 0.10), ("RightUpperLeg", "RightLowerLeg", 0.085), ("RightLowerLeg", "RightFoot", 0.06),
    ("RightFoot", "RightToe", 0.045),
    ("Pelvis", "LeftUpperLeg", 0.10), ("LeftUpperLeg", "LeftLowerLeg", 0.085), ("LeftLowerLeg", "LeftFoot", 0.06),
    ("LeftFoot", "LeftToe", 0.045),
)  # fmt: skip
#: Extensions ``segment -> (parent whose direction is continued, length m)``: the head above the neck joint,
#: the hand beyond the wrist.
CAPSULE_EXTENSIONS = {"Head": ("Neck", 0.16), "RightHand": ("RightForeArm", 0.10), "LeftHand": ("LeftForeArm", 0.10)}

#: Fields that hold signed numbers, integers or structures rather than non-negative scalars.
_STRUCTURED = ("frame_tilt_azimuth_deg", "stations", "field_seed")


@dataclass(frozen=True)
class TrackerErrorModel:
    """Noise, mounting spread, tracking loss and (off by default) the biases of real trackers; see
    the module docstring for the model and the sources of the defaults and ranges. The defaults are
    the ``ideal`` preset; :meth:`realistic` draws the ``realistic`` one."""

    #: White position noise per axis, m (Niehorster et al. 2017; Merker et al. 2023).
    position_noise_m: float = 0.001
    #: RMS angle of the white orientation noise, deg (sub-degree; Niehorster et al. 2017).
    orientation_noise_deg: float = 0.3
    #: White velocity noise per axis, m/s (assumption).
    velocity_noise_m_s: float = 0.01
    #: White angular-velocity noise per axis, rad/s (assumption).
    angular_velocity_noise_rad_s: float = 0.02
    #: Std per axis of the mounting translation around its nominal site, m.
    mount_translation_sigma_m: float = 0.01
    #: RMS angle of the mounting rotation (tracker frame in segment frame), deg.
    mount_rotation_deg: float = 10.0
    #: Tracking-loss events per minute of tracked time, per tracker (assumption for close contact).
    loss_rate_per_min: float = 2.0
    #: Range of loss durations, s, drawn log-uniformly (tens to hundreds of ms; assumption).
    loss_duration_s: tuple[float, float] = (0.02, 0.4)
    #: Fraction of loss events reported as a jump to the origin with ``valid`` True.
    loss_origin_fraction: float = 0.3
    #: 3-D RMS of the correlated (Gauss-Markov) position error, m; 0 = off.
    correlated_error_m: float = 0.0
    #: Correlation time of the correlated error, s.
    correlated_error_tau_s: float = 1.0
    #: Vertical to horizontal std of the correlated error and the acquisition offset.
    vertical_ratio: float = 1.0
    #: 3-D RMS of the offset drawn at every acquisition (start and after each loss), m; 0 = off.
    acquisition_offset_m: float = 0.0
    #: Tilt of the reported frame about a horizontal axis through the origin, deg; 0 = off.
    frame_tilt_deg: float = 0.0
    #: Azimuth of the tilt axis, deg from +X towards +Z.
    frame_tilt_azimuth_deg: float = 0.0
    #: RMS per axis of the smooth displacement field of the tracking space, m; 0 = off.
    field_distortion_m: float = 0.0
    #: Wavelength of the displacement field's plane waves, m.
    field_wavelength_m: float = 6.0
    #: Seed of the displacement field's directions and phases (one field per lighthouse system).
    field_seed: int = 0
    #: Lighthouse base stations, world positions, m; empty = no occlusion.
    stations: tuple[tuple[float, float, float], ...] = ()
    #: Time after a hidden tracker is seen again until it is tracked again, s.
    reacquire_delay_s: float = 0.0
    #: Position jumps per minute of tracked time, per tracker; 0 = off.
    jump_rate_per_min: float = 0.0
    #: Range of jump lengths, m, drawn log-uniformly.
    jump_size_m: tuple[float, float] = (0.01, 0.05)
    #: Range of jump durations, s, drawn log-uniformly.
    jump_duration_s: tuple[float, float] = (0.01, 0.2)
    #: Std per axis of one strap slip step (segment frame), m; 0 = off.
    strap_slip_m: float = 0.0
    #: Distance from the tracker to the partner's body under which the strap is in contact, m.
    slip_contact_m: float = 0.05

    def __post_init__(self):
        try:  # lists (e.g. read back from JSON) as tuples, so that the model stays hashable
            for name in ("loss_duration_s", "jump_size_m", "jump_duration_s"):
                object.__setattr__(self, name, tuple(float(v) for v in getattr(self, name)))
            object.__setattr__(self, "stations", tuple(tuple(float(v) for v in st) for st in self.stations))
        except (TypeError, ValueError):
            raise ValueError(f"TrackerErrorModel: ranges must be (min, max) pairs and stations (x, y, z) positions, "
                             f"got {self.loss_duration_s!r}, {self.jump_size_m!r}, {self.jump_duration_s!r}, "
                             f"{self.stations!r}") from None  # fmt: skip
        for name in self.__dataclass_fields__:
            if name in _STRUCTURED:
                continue
            value = getattr(self, name)
            values = value if isinstance(value, tuple) else (value,)
            if not all(v >= 0 and math.isfinite(v) for v in values):
                raise ValueError(f"TrackerErrorModel.{name} must be finite and non-negative, got {value}")
        for name in ("loss_duration_s", "jump_size_m", "jump_duration_s"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"{name} must be (min, max) with 0 < min <= max, got {getattr(self, name)}")
        if self.loss_origin_fraction > 1:
            raise ValueError(f"loss_origin_fraction must be in [0, 1], got {self.loss_origin_fraction}")
        if not math.isfinite(self.frame_tilt_azimuth_deg):
            raise ValueError(f"frame_tilt_azimuth_deg must be finite, got {self.frame_tilt_azimuth_deg}")
        for name in ("correlated_error_tau_s", "field_wavelength_m", "vertical_ratio"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if not (isinstance(self.field_seed, (int, np.integer)) and self.field_seed >= 0):
            raise ValueError(f"field_seed must be a non-negative integer, got {self.field_seed!r}")
        if not all(len(st) == 3 and all(math.isfinite(v) for v in st) for st in self.stations):
            raise ValueError(f"stations must be (x, y, z) positions in metres, got {self.stations!r}")

    @classmethod
    def ideal(cls) -> "TrackerErrorModel":
        """Noise-free trackers that never lose tracking (mounts still drawn around their sites)."""
        return cls(position_noise_m=0.0, orientation_noise_deg=0.0, velocity_noise_m_s=0.0,
                   angular_velocity_noise_rad_s=0.0, loss_rate_per_min=0.0)  # fmt: skip

    @classmethod
    def realistic(cls, rng: np.random.Generator) -> "TrackerErrorModel":
        """Every parameter drawn once (one take, shared by every tracker of the lighthouse system)
        uniformly within :data:`REALISTIC_RANGES`, including the station layout: two stations at
        opposite corners of a square room (half-size, height, azimuth of the diagonal)."""
        d = {name: float(rng.uniform(lo, hi)) for name, (lo, hi) in REALISTIC_RANGES.items()}
        half, height, az = d.pop("station_half_size_m"), d.pop("station_height_m"), d.pop("station_azimuth_deg")
        c, s = half * math.cos(math.radians(az)), half * math.sin(math.radians(az))
        stations = ((c - s, height, s + c), (s - c, height, -s - c))  # the corners (+-half, +-half) turned by az
        return cls(**d, field_seed=int(rng.integers(0, 2**31)), stations=stations)

    @property
    def occlusion_enabled(self) -> bool:
        """Whether losses follow occlusion by the partner's body (stations given)."""
        return len(self.stations) > 0


def realistic_tracker_clock(rng: np.random.Generator) -> DeviceClock:
    """A lighthouse system's clock behind an OpenVR bridge, drawn once per take (module docstring):
    latency 15-30 ms, exponential jitter of mean 1-4 ms, offset 0-10 s, drift -50..+50 ppm."""
    offset_s, drift_ppm = float(rng.uniform(0.0, 10.0)), float(rng.uniform(-50.0, 50.0))
    latency_s, jitter_s = float(rng.uniform(0.015, 0.030)), float(rng.uniform(0.001, 0.004))
    return DeviceClock(offset_s=offset_s, drift_ppm=drift_ppm, latency_s=latency_s, jitter_s=jitter_s)


@dataclass(eq=False)
class TrackerStream:
    """``N`` trackers' simulated samples and the truth behind them.

    Reported (``T`` samples per tracker): ``device_time_ns (T,)`` on the tracker clock (shared by
    the trackers of one system); ``host_time_ns (N, T)``; ``valid (N, T)``; ``position (N, T, 3)``
    m, ``orientation (N, T, 4)`` xyzw, ``velocity (N, T, 3)`` m/s, ``angular_velocity (N, T, 3)``
    rad/s, all in the world frame. Iterating yields :class:`TrackerSample`\\ s sorted by host time
    (arrival order).

    Truth: ``true_time_ns (T,)`` scene times; ``true_position``, ``true_orientation``,
    ``true_velocity``, ``true_angular_velocity``; ``mount_rotation (N, 4)`` and
    ``mount_translation (N, 3)`` (tracker in segment frame); ``lost (N, T)`` samples inside a loss
    event; the events ``loss_tracker (E,)`` index, ``loss_start_ns``/``loss_stop_ns (E,)`` scene
    times (stop exclusive), ``loss_mode (E,)`` ``"invalid"`` or ``"origin"``, ``loss_cause (E,)``
    ``"random"`` or ``"hidden"`` (occlusion by the partner); ``hidden (N, T)`` samples whose every
    line of sight is blocked by the partner; ``mount_slip (N, T, 3)`` the strap slip added to the
    mount translation (segment frame, m; zeros when off); ``clock``, ``errors``. ``true_position``
    is the tracker's real position, slip included.
    """

    serials: tuple[str, ...]
    segments: tuple[str, ...]
    rate_hz: float
    device_time_ns: np.ndarray
    host_time_ns: np.ndarray
    valid: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray
    true_time_ns: np.ndarray
    true_position: np.ndarray
    true_orientation: np.ndarray
    true_velocity: np.ndarray
    true_angular_velocity: np.ndarray
    mount_rotation: np.ndarray
    mount_translation: np.ndarray
    lost: np.ndarray
    loss_tracker: np.ndarray
    loss_start_ns: np.ndarray
    loss_stop_ns: np.ndarray
    loss_mode: np.ndarray
    loss_cause: np.ndarray
    hidden: np.ndarray
    mount_slip: np.ndarray
    clock: DeviceClock
    errors: TrackerErrorModel

    def __len__(self) -> int:
        return self.valid.size

    def index(self, serial: str) -> int:
        try:
            return self.serials.index(serial)
        except ValueError:
            raise KeyError(f"no tracker {serial!r}; this stream has {list(self.serials)}") from None

    def sample(self, i: int, k: int) -> TrackerSample:
        """Sample ``k`` of tracker index ``i`` as the typed :class:`TrackerSample` a decoder yields."""
        return TrackerSample(serial=self.serials[i], valid=bool(self.valid[i, k]),
                             device_time_ns=int(self.device_time_ns[k]), host_time_ns=int(self.host_time_ns[i, k]),
                             position=self.position[i, k], orientation=self.orientation[i, k],
                             velocity=self.velocity[i, k], angular_velocity=self.angular_velocity[i, k])  # fmt: skip

    def __iter__(self) -> Iterator[TrackerSample]:
        N, T = self.valid.shape
        tracker = np.repeat(np.arange(N), T)
        k = np.tile(np.arange(T), N)
        order = np.lexsort((tracker, k, self.host_time_ns.ravel()))
        return (self.sample(int(tracker[j]), int(k[j])) for j in order)


def _loss_events(rng: np.random.Generator, t0_ns: int, t1_ns: int, errors: TrackerErrorModel) -> list[tuple]:
    """``[(start_ns, stop_ns, mode), ...]`` on the scene clock: Poisson arrivals during tracked time."""
    if errors.loss_rate_per_min <= 0:
        return []
    mean_gap_ns = 60e9 / errors.loss_rate_per_min
    lo, hi = (math.log(v) for v in errors.loss_duration_s)
    events, t = [], float(t0_ns)
    while True:
        t += rng.exponential(mean_gap_ns)
        if t >= t1_ns:
            return events
        stop = t + math.exp(rng.uniform(lo, hi)) * 1e9
        mode = "origin" if rng.random() < errors.loss_origin_fraction else "invalid"
        events.append((int(round(t)), int(round(stop)), mode))
        t = stop


def _segment_distance(p1, q1, p2, q2) -> np.ndarray:
    """Distance between segments ``p1 q1`` and ``p2 q2`` (broadcast ``(..., 3)`` -> ``(...)``): the
    closest points of Ericson, "Real-Time Collision Detection", sec. 5.1.9, vectorised."""
    d1, d2, r = q1 - p1, q2 - p2, p1 - p2
    a, e = np.einsum("...i,...i", d1, d1), np.einsum("...i,...i", d2, d2)
    b, c, f = np.einsum("...i,...i", d1, d2), np.einsum("...i,...i", d1, r), np.einsum("...i,...i", d2, r)
    eps = 1e-12
    a_, e_ = np.maximum(a, eps), np.maximum(e, eps)
    denom = a * e - b * b
    s = np.where(denom > eps, np.clip((b * f - c * e) / np.maximum(denom, eps), 0.0, 1.0), 0.0)
    s = np.where(e > eps, s, np.clip(-c / a_, 0.0, 1.0))
    t = np.where(e > eps, (b * s + f) / e_, 0.0)
    s = np.where(t < 0, np.clip(-c / a_, 0.0, 1.0), np.where(t > 1, np.clip((b - c) / a_, 0.0, 1.0), s))
    s = np.where(a > eps, s, 0.0)
    t = np.clip(np.where(a > eps, t, f / e_), 0.0, 1.0)
    t = np.where(e > eps, t, 0.0)
    return np.linalg.norm(p1 + d1 * s[..., None] - (p2 + d2 * t[..., None]), axis=-1)


def occluder_capsules(segment_names, positions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The partner's body, from its segment origins ``positions (T, S, 3)`` (named ``segment_names``),
    as capsules (:data:`OCCLUDER_CAPSULES`): ``(start (T, C, 3), end (T, C, 3), radius (C,))``, world, m."""
    idx = {name: i for i, name in enumerate(segment_names)}
    pos = positions
    starts, ends, radii = [], [], []
    for a, b, radius in OCCLUDER_CAPSULES:
        p = pos[:, idx[a]]
        if b is None:
            parent, length = CAPSULE_EXTENSIONS[a]
            axis = p - pos[:, idx[parent]]
            q = p + axis * (length / np.maximum(np.linalg.norm(axis, axis=-1, keepdims=True), 1e-9))
        else:
            q = pos[:, idx[b]]
        starts.append(p), ends.append(q), radii.append(radius)
    return np.stack(starts, 1), np.stack(ends, 1), np.asarray(radii)


def line_of_sight_blocked(points: np.ndarray, stations, capsules, chunk: int = 4096) -> np.ndarray:
    """``(T, K)`` bool: whether the segment from ``points (T, 3)`` to station ``k`` of ``stations (K, 3)``
    passes through one of ``capsules`` (:func:`occluder_capsules` at the same ``T`` samples)."""
    start, end, radius = capsules
    stations = np.asarray(stations, dtype=np.float64).reshape(-1, 3)
    out = np.zeros((len(points), len(stations)), dtype=bool)
    for lo in range(0, len(points), chunk):
        sl = slice(lo, lo + chunk)
        p = points[sl, None, :]
        for k, st in enumerate(stations):
            dist = _segment_distance(p, np.broadcast_to(st, p.shape), start[sl], end[sl])
            out[sl, k] = (dist < radius).any(axis=1)
    return out


def distance_to_body(points: np.ndarray, capsules, chunk: int = 4096) -> np.ndarray:
    """``(T,)`` distance (m) from ``points (T, 3)`` to the capsules' surface (negative inside)."""
    start, end, radius = capsules
    out = np.empty(len(points))
    for lo in range(0, len(points), chunk):
        sl = slice(lo, lo + chunk)
        p = points[sl, None, :]
        out[sl] = (_segment_distance(p, p, start[sl], end[sl]) - radius).min(axis=1)
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """``[(first, stop), ...]`` sample index ranges (stop exclusive) where ``mask`` is True."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist()))


def _hidden_events(hidden: np.ndarray, times: np.ndarray, t1_ns: int, errors: TrackerErrorModel) -> list[tuple]:
    """Loss events ``(start_ns, stop_ns)`` of one tracker from its ``hidden (T,)`` samples: hidden spells
    longer than :data:`IMU_BRIDGE_S`, lasting until ``reacquire_delay_s`` after the tracker is seen
    again (merged where they overlap)."""
    events = []
    for first, stop in _runs(hidden):
        end_ns = int(times[stop]) if stop < len(times) else int(t1_ns) + 1
        if end_ns - int(times[first]) < IMU_BRIDGE_S * 1e9:
            continue
        end_ns += int(round(errors.reacquire_delay_s * 1e9))
        if events and int(times[first]) <= events[-1][1]:
            events[-1] = (events[-1][0], max(events[-1][1], end_ns))
        else:
            events.append((int(times[first]), end_ns))
    return events


def _poisson_spells(rng: np.random.Generator, t0_ns: int, t1_ns: int, rate_per_min: float,
                    duration_s: tuple[float, float]) -> list[tuple[int, int]]:  # fmt: skip
    """``[(start_ns, stop_ns), ...]``: Poisson arrivals at ``rate_per_min``, log-uniform durations."""
    if rate_per_min <= 0:
        return []
    lo, hi = (math.log(v) for v in duration_s)
    spells, t = [], float(t0_ns)
    while True:
        t += rng.exponential(60e9 / rate_per_min)
        if t >= t1_ns:
            return spells
        stop = t + math.exp(rng.uniform(lo, hi)) * 1e9
        spells.append((int(round(t)), int(round(stop))))
        t = stop


def displacement_field(errors: TrackerErrorModel):
    """The smooth displacement ``d(p)`` of the tracking space (module docstring) as a function of
    ``points (..., 3)`` -> ``(..., 3)`` m, or None when ``field_distortion_m`` is 0."""
    if errors.field_distortion_m <= 0:
        return None
    rng = np.random.default_rng(np.random.SeedSequence([int(errors.field_seed), 0xF1E1D]))
    k = rng.normal(size=(3, FIELD_MODES, 3))
    k *= (2 * math.pi / errors.field_wavelength_m) / np.linalg.norm(k, axis=-1, keepdims=True)
    phase = rng.uniform(0.0, 2 * math.pi, (3, FIELD_MODES))
    amp = rng.normal(0.0, errors.field_distortion_m * math.sqrt(2.0 / FIELD_MODES), (3, FIELD_MODES))

    def field(points: np.ndarray) -> np.ndarray:
        arg = np.einsum("...j,amj->...am", points, k) + phase
        return np.einsum("...am,am->...a", np.sin(arg), amp)

    return field


def frame_tilt(errors: TrackerErrorModel) -> Rotation | None:
    """The tilt ``T`` of the reported frame (module docstring), or None when ``frame_tilt_deg`` is 0."""
    if errors.frame_tilt_deg <= 0:
        return None
    az = math.radians(errors.frame_tilt_azimuth_deg)
    return Rotation.from_rotvec(math.radians(errors.frame_tilt_deg) * np.array([math.cos(az), 0.0, math.sin(az)]))


def _axis_scale(errors: TrackerErrorModel) -> np.ndarray:
    """Per-axis std of an error of 3-D RMS 1 with vertical to horizontal ratio ``vertical_ratio``."""
    k = errors.vertical_ratio
    return np.array([1.0, k, 1.0]) / math.sqrt(2.0 + k * k)


def _slip(rng: np.random.Generator, times: np.ndarray, distance: np.ndarray, errors: TrackerErrorModel) -> np.ndarray:
    """Strap slip ``(T, 3)`` (segment frame, m) from the partner's distance ``(T,)`` to the tracker."""
    slip = np.zeros((len(times), 3))
    inside = distance < errors.slip_contact_m
    leave = distance > 2 * errors.slip_contact_m
    onsets, touching = [], False
    for k in np.flatnonzero(inside | leave):  # hysteresis: enter under the threshold, leave over twice it
        if inside[k] and not touching:
            onsets.append(k)
        touching = bool(inside[k]) or (touching and not leave[k])
    target = np.zeros(3)
    for k in onsets:
        new = target + rng.normal(0.0, errors.strap_slip_m, 3)
        norm = float(np.linalg.norm(new))
        if norm > SLIP_MAX_M:
            new *= SLIP_MAX_M / norm
        ramp = np.clip((times - times[k]) * 1e-9 / SLIP_RAMP_S, 0.0, 1.0)
        slip += ramp[:, None] * (new - target)
        target = new
    return slip


def simulate_trackers(gt: SkeletonTrack | KinematicSpline, sites: dict[str, str] | None = None, rate_hz: float = 250.0,
                      errors: TrackerErrorModel = TrackerErrorModel(), seed: int = 0,
                      clock: DeviceClock = DEFAULT_TRACKER_CLOCK,
                      occluder: SkeletonTrack | KinematicSpline | None = None) -> TrackerStream:  # fmt: skip
    """Simulate trackers on ground truth ``gt`` (a :class:`SkeletonTrack` or a
    :class:`KinematicSpline` of one). ``sites``: serial -> segment name (default
    :func:`default_sites` with the actor's name, upper-cased, as prefix). Each tracker's mount,
    noise and losses come from ``seed`` and its serial alone, so adding a tracker leaves the
    others unchanged. ``occluder``: the partner's 23 MVN segments on the same scene clock (held
    at its first and last frame outside its track); it hides trackers and makes straps slip only where
    ``errors`` has ``stations`` (occlusion) or ``strap_slip_m`` (slip). ``gt`` is never modified."""
    spline = as_spline(gt)
    if sites is None:
        sites = default_sites(spline.track.actor.upper() or "SIM")
    if not sites:
        raise ValueError("no tracker sites given")
    serials = tuple(str(s) for s in sites)
    segments = tuple(sites[s] for s in serials)
    seg_idx = [spline.track.segment_index(s) for s in segments]
    device_ns, true_ns = clock.sample_times(spline.t0_ns, spline.t1_ns, rate_hz)
    kin = spline.evaluate(true_ns)
    true_times = kin.times_ns
    N, T = len(serials), kin.num_samples

    capsules = None
    if occluder is not None and (errors.occlusion_enabled or errors.strap_slip_m > 0):
        partner = as_spline(occluder)
        missing = [s for s, _, _ in OCCLUDER_CAPSULES if s not in partner.segment_names]
        if missing:
            raise ValueError(f"the occluder must have the MVN segments; it lacks {missing[:3]}")
        # the partner's frames interpolated linearly (capsules need positions only; scene rates suffice)
        track = partner.track
        frames = track.positions.reshape(track.num_frames, -1)
        t_ns = track.device_time_ns.astype(np.float64)
        at = np.stack([np.interp(true_ns, t_ns, frames[:, j]) for j in range(frames.shape[1])], 1)
        capsules = occluder_capsules(track.segment_names, at.reshape(len(true_ns), -1, 3))
    field, tilt = displacement_field(errors), frame_tilt(errors)

    shape = {"pos": (N, T, 3), "quat": (N, T, 4)}
    true_p, true_v, true_w = (np.empty(shape["pos"]) for _ in range(3))
    true_q = np.empty(shape["quat"])
    pos, vel, ang = (np.empty(shape["pos"]) for _ in range(3))
    quat = np.empty(shape["quat"])
    valid = np.ones((N, T), dtype=bool)
    lost = np.zeros((N, T), dtype=bool)
    hidden = np.zeros((N, T), dtype=bool)
    slip = np.zeros((N, T, 3))
    host = np.empty((N, T), dtype=np.int64)
    mount_q, mount_t = np.empty((N, 4)), np.empty((N, 3))
    events = []
    sigma_r = math.radians(errors.orientation_noise_deg) / math.sqrt(3.0)
    dt_s = 1.0 / rate_hz

    for i, (serial, seg) in enumerate(zip(serials, seg_idx)):
        streams = np.random.SeedSequence([int(seed), zlib.crc32(serial.encode()), 0x71BE]).spawn(4)
        r_mount, r_noise, r_loss, r_host = (np.random.default_rng(s) for s in streams)
        extra = np.random.SeedSequence([int(seed), zlib.crc32(serial.encode()), 0x8EA1]).spawn(4)
        r_bias, r_acq, r_jump, r_slip = (np.random.default_rng(s) for s in extra)
        nominal = np.asarray(tracker_site(segments[i]))
        mount_t[i] = nominal + r_mount.normal(0.0, errors.mount_translation_sigma_m, 3)
        m_rot = random_rotations(r_mount, 1, errors.mount_rotation_deg)[0]
        mount_q[i] = m_rot.as_quat()
        p, v, _ = kin.point(seg, mount_t[i])
        r_seg = kin.rotations(seg)
        if capsules is not None and errors.strap_slip_m > 0:
            slip[i] = _slip(r_slip, true_times, distance_to_body(p, capsules), errors)
            moved = r_seg.apply(slip[i])
            p, v = p + moved, v + np.cross(kin.angular_velocity_world[:, seg], moved)
        r_tr = r_seg * m_rot
        true_p[i], true_v[i], true_q[i] = p, v, r_tr.as_quat()
        true_w[i] = kin.angular_velocity_world[:, seg]

        pos[i] = p + r_noise.normal(0.0, errors.position_noise_m, (T, 3))
        quat[i] = (r_tr * Rotation.from_rotvec(r_noise.normal(0.0, sigma_r, (T, 3)))).as_quat()
        vel[i] = v + r_noise.normal(0.0, errors.velocity_noise_m_s, (T, 3))
        ang[i] = true_w[i] + r_noise.normal(0.0, errors.angular_velocity_noise_rad_s, (T, 3))

        randoms = _loss_events(r_loss, spline.t0_ns, spline.t1_ns, errors)
        mine = [(start, stop, mode, "random") for start, stop, mode in randoms]
        if capsules is not None and errors.occlusion_enabled:
            hidden[i] = line_of_sight_blocked(p, errors.stations, capsules).all(axis=1)
            spells = _hidden_events(hidden[i], true_times, spline.t1_ns, errors)
            mine = sorted(mine + [(start, stop, "invalid", "hidden") for start, stop in spells], key=lambda e: e[0])

        # the biases of the tracking space and of each acquisition (off in the ideal preset)
        if field is not None:
            pos[i] += field(p)
        if tilt is not None:
            pos[i] = tilt.apply(pos[i])
            quat[i] = (tilt * Rotation.from_quat(quat[i])).as_quat()
            vel[i], ang[i] = tilt.apply(vel[i]), tilt.apply(ang[i])
        scale = _axis_scale(errors)
        if errors.correlated_error_m > 0:
            pos[i] += scale * gauss_markov(r_bias, T, (3,), errors.correlated_error_m, errors.correlated_error_tau_s,
                                           dt_s)  # fmt: skip
        if errors.acquisition_offset_m > 0:
            ends = np.sort(np.asarray([stop for _, stop, _, _ in mine], dtype=np.int64))
            acquisition = np.searchsorted(ends, true_times, side="right")
            pos[i] += (scale * r_acq.normal(0.0, errors.acquisition_offset_m, (len(ends) + 1, 3)))[acquisition]
        for start, stop in _poisson_spells(r_jump, spline.t0_ns, spline.t1_ns, errors.jump_rate_per_min,
                                           errors.jump_duration_s):  # fmt: skip
            direction = r_jump.normal(size=3)
            length = math.exp(r_jump.uniform(*(math.log(x) for x in errors.jump_size_m)))
            pos[i, (true_times >= start) & (true_times < stop)] += length * direction / np.linalg.norm(direction)

        for start, stop, mode, cause in mine:
            inside = (true_times >= start) & (true_times < stop)
            events.append((i, start, stop, mode, cause))
            if not inside.any():
                continue
            first = int(np.flatnonzero(inside)[0])
            lost[i, inside] = True
            if mode == "origin":
                pos[i, inside], vel[i, inside], ang[i, inside] = 0.0, 0.0, 0.0
                quat[i, inside] = (0.0, 0.0, 0.0, 1.0)
            else:
                valid[i, inside] = False
                tracked = np.flatnonzero(~lost[i, :first])
                if tracked.size:  # OpenVR keeps reporting the last tracked pose while the flag is down
                    last = int(tracked[-1])
                    pos[i, inside], quat[i, inside] = pos[i, last], quat[i, last]
                    vel[i, inside], ang[i, inside] = vel[i, last], ang[i, last]
                else:
                    pos[i, inside], vel[i, inside], ang[i, inside] = 0.0, 0.0, 0.0
                    quat[i, inside] = (0.0, 0.0, 0.0, 1.0)
        host[i] = clock.host_time_ns(true_ns, r_host)

    ev = list(zip(*events)) if events else [(), (), (), (), ()]
    stream = TrackerStream(
        serials=serials, segments=segments, rate_hz=float(rate_hz), device_time_ns=device_ns, host_time_ns=host,
        valid=valid, position=pos, orientation=quat, velocity=vel, angular_velocity=ang, true_time_ns=true_times,
        true_position=true_p, true_orientation=true_q, true_velocity=true_v, true_angular_velocity=true_w,
        mount_rotation=mount_q, mount_translation=mount_t, lost=lost,
        loss_tracker=np.asarray(ev[0], dtype=np.int64), loss_start_ns=np.asarray(ev[1], dtype=np.int64),
        loss_stop_ns=np.asarray(ev[2], dtype=np.int64), loss_mode=np.asarray(ev[3], dtype="<U7"),
        loss_cause=np.asarray(ev[4], dtype="<U6"), hidden=hidden, mount_slip=slip, clock=clock, errors=errors,
    )  # fmt: skip
    freeze_arrays(stream)
    return stream

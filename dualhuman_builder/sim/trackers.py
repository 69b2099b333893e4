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

Defaults and their sources:

* 1 mm position noise per axis, 0.3 deg RMS orientation noise: Niehorster, Li & Lappe, "The
  Accuracy and Precision of Position and Orientation Tracking in the HTC Vive Virtual Reality
  System for Scientific Research", i-Perception 8(3), 2017, find the Vive's precision high and
  its latency 22 ms; Bauer,
  Lienhart & Jost, Sensors 21(5):1622, 2021, find position readings reproducible within a few
  millimetres but systematic effects of centimetres and a 0.4 deg tilt of the reference frame;
  Sansone et al., Virtual Reality (2021), doi:10.1007/s10055-021-00584-5, give a static
  accuracy of 0.5 +- 0.2 cm horizontally; Merker et al., Sensors 23(17):7371, 2023, compare VIVE
  Tracker 3.0 with Vicon on a moving body. 1 mm white noise is our choice for a strapped, moving
  tracker; the sub-degree orientation noise our reading of the same studies. Systematic offsets
  and the frame tilt are biases left to calibration and not modelled here.
* loss: 2 events per minute lasting 20-400 ms: assumptions for two people in close contact
  occluding each other. Niehorster et al. also found
  the tracking space offset changes after a loss; that is not modelled.
* clock: 30 ppm drift, a typical crystal tolerance (the Awinda station, the suit's clock, is
  specified by Xsens at <= 1 ppm), and an arbitrary 0.25 s offset — OpenVR exposes no
  device time (openvr #1007); libsurvive's tracker timecode counts from power-on.
* velocity noise 0.01 m/s and angular-velocity noise 0.02 rad/s: assumptions (OpenVR's velocities
  are filter outputs).
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass
from typing import Iterator

import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.samples import TrackerSample
from dualhuman_builder.sim.imu import freeze_arrays
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


@dataclass(frozen=True)
class TrackerErrorModel:
    """Noise, mounting spread and tracking loss of simulated trackers; see the module docstring
    for the model and the sources of the defaults."""

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

    def __post_init__(self):
        for name in self.__dataclass_fields__:
            value = getattr(self, name)
            values = value if isinstance(value, tuple) else (value,)
            if not all(v >= 0 and math.isfinite(v) for v in values):
                raise ValueError(f"TrackerErrorModel.{name} must be finite and non-negative, got {value}")
        lo, hi = self.loss_duration_s
        if not 0 < lo <= hi:
            raise ValueError(f"loss_duration_s must be (min, max) with 0 < min <= max, got {self.loss_duration_s}")
        if self.loss_origin_fraction > 1:
            raise ValueError(f"loss_origin_fraction must be in [0, 1], got {self.loss_origin_fraction}")

    @classmethod
    def ideal(cls) -> "TrackerErrorModel":
        """Noise-free trackers that never lose tracking (mounts still drawn around their sites)."""
        return cls(position_noise_m=0.0, orientation_noise_deg=0.0, velocity_noise_m_s=0.0,
                   angular_velocity_noise_rad_s=0.0, loss_rate_per_min=0.0)  # fmt: skip


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
    times (stop exclusive), ``loss_mode (E,)`` ``"invalid"`` or ``"origin"``; ``clock``, ``errors``.
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


def simulate_trackers(gt: SkeletonTrack | KinematicSpline, sites: dict[str, str] | None = None, rate_hz: float = 250.0,
                      errors: TrackerErrorModel = TrackerErrorModel(), seed: int = 0,
                      clock: DeviceClock = DEFAULT_TRACKER_CLOCK) -> TrackerStream:  # fmt: skip
    """Simulate trackers on ground truth ``gt`` (a :class:`SkeletonTrack` or a
    :class:`KinematicSpline` of one). ``sites``: serial -> segment name (default
    :func:`default_sites` with the actor's name, upper-cased, as prefix). Each tracker's mount,
    noise and losses come from ``seed`` and its serial alone, so adding a tracker leaves the
    others unchanged. ``gt`` is never modified."""
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

    shape = {"pos": (N, T, 3), "quat": (N, T, 4)}
    true_p, true_v, true_w = (np.empty(shape["pos"]) for _ in range(3))
    true_q = np.empty(shape["quat"])
    pos, vel, ang = (np.empty(shape["pos"]) for _ in range(3))
    quat = np.empty(shape["quat"])
    valid = np.ones((N, T), dtype=bool)
    lost = np.zeros((N, T), dtype=bool)
    host = np.empty((N, T), dtype=np.int64)
    mount_q, mount_t = np.empty((N, 4)), np.empty((N, 3))
    ev_tracker, ev_start, ev_stop, ev_mode = [], [], [], []
    sigma_r = math.radians(errors.orientation_noise_deg) / math.sqrt(3.0)

    for i, (serial, seg) in enumerate(zip(serials, seg_idx)):
        streams = np.random.SeedSequence([int(seed), zlib.crc32(serial.encode()), 0x71BE]).spawn(4)
        r_mount, r_noise, r_loss, r_host = (np.random.default_rng(s) for s in streams)
        nominal = np.asarray(tracker_site(segments[i]))
        mount_t[i] = nominal + r_mount.normal(0.0, errors.mount_translation_sigma_m, 3)
        m_rot = random_rotations(r_mount, 1, errors.mount_rotation_deg)[0]
        mount_q[i] = m_rot.as_quat()
        p, v, _ = kin.point(seg, mount_t[i])
        r_tr = kin.rotations(seg) * m_rot
        true_p[i], true_v[i], true_q[i] = p, v, r_tr.as_quat()
        true_w[i] = kin.angular_velocity_world[:, seg]

        pos[i] = p + r_noise.normal(0.0, errors.position_noise_m, (T, 3))
        quat[i] = (r_tr * Rotation.from_rotvec(r_noise.normal(0.0, sigma_r, (T, 3)))).as_quat()
        vel[i] = v + r_noise.normal(0.0, errors.velocity_noise_m_s, (T, 3))
        ang[i] = true_w[i] + r_noise.normal(0.0, errors.angular_velocity_noise_rad_s, (T, 3))

        for start, stop, mode in _loss_events(r_loss, spline.t0_ns, spline.t1_ns, errors):
            inside = (true_times >= start) & (true_times < stop)
            ev_tracker.append(i), ev_start.append(start), ev_stop.append(stop), ev_mode.append(mode)
            if not inside.any():
                continue
            lost[i, inside] = True
            if mode == "origin":
                pos[i, inside], vel[i, inside], ang[i, inside] = 0.0, 0.0, 0.0
                quat[i, inside] = (0.0, 0.0, 0.0, 1.0)
            else:
                valid[i, inside] = False
                tracked = np.flatnonzero(~lost[i, : int(np.flatnonzero(inside)[0])])
                if tracked.size:  # OpenVR keeps reporting the last tracked pose while the flag is down
                    last = int(tracked[-1])
                    pos[i, inside], quat[i, inside] = pos[i, last], quat[i, last]
                    vel[i, inside], ang[i, inside] = vel[i, last], ang[i, last]
                else:
                    pos[i, inside], vel[i, inside], ang[i, inside] = 0.0, 0.0, 0.0
                    quat[i, inside] = (0.0, 0.0, 0.0, 1.0)
        host[i] = clock.host_time_ns(true_ns, r_host)

    stream = TrackerStream(
        serials=serials, segments=segments, rate_hz=float(rate_hz), device_time_ns=device_ns, host_time_ns=host,
        valid=valid, position=pos, orientation=quat, velocity=vel, angular_velocity=ang, true_time_ns=true_times,
        true_position=true_p, true_orientation=true_q, true_velocity=true_v, true_angular_velocity=true_w,
        mount_rotation=mount_q, mount_translation=mount_t, lost=lost,
        loss_tracker=np.asarray(ev_tracker, dtype=np.int64), loss_start_ns=np.asarray(ev_start, dtype=np.int64),
        loss_stop_ns=np.asarray(ev_stop, dtype=np.int64), loss_mode=np.asarray(ev_mode, dtype="<U7"),
        clock=clock, errors=errors,
    )  # fmt: skip
    freeze_arrays(stream)
    return stream

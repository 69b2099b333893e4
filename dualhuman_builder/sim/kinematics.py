"""Smooth resampling of a ground-truth :class:`~dualhuman_builder.tracks.SkeletonTrack` and its
derivatives, and the device clocks that stamp simulated samples.

Ground truth comes at scene rates (30-60 fps); devices sample at 240 Hz (suit), 250 Hz (trackers),
400 or 100 Hz (MTi). :class:`KinematicSpline` fits, per segment, a cubic spline to the positions
(:class:`scipy.interpolate.CubicSpline`, not-a-knot ends) and a rotation spline to the orientations
(:class:`scipy.spatial.transform.RotationSpline`, continuous angular rate and acceleration), and
evaluates both and their analytic derivatives at any times inside the track.

Frames (all quantities of a segment ``s`` at time ``t``):

* ``orientations (T, S, 4)`` xyzw: ``R`` maps segment-frame vectors to world (Y-up) vectors;
* ``positions (T, S, 3)``, ``velocity``, ``acceleration``: the segment origin in the world frame,
  m, m/s, m/s^2;
* ``angular_velocity_body`` rad/s and ``angular_acceleration_body`` rad/s^2: in the segment frame
  (what a gyroscope fixed to the segment measures), as RotationSpline returns them;
* ``angular_velocity_world = R @ angular_velocity_body`` and likewise the angular acceleration
  (``d(R w_b)/dt = R (w_b x w_b + dw_b/dt) = R dw_b/dt``).

Time axis: the track's ``device_time_ns`` (for ground truth both of its clocks are the scene
clock). Times are int64 ns outside, float seconds since the track's first frame inside the splines.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, RotationSpline

from dualhuman_builder.tracks import SkeletonTrack

_PER_SEGMENT = ("orientations", "positions", "velocity", "acceleration", "angular_velocity_world",
                "angular_velocity_body", "angular_acceleration_world", "angular_acceleration_body")

#: Slack (ns) allowed when an evaluation time falls just outside the track through rounding.
_EDGE_SLACK_NS = 1000


@dataclass(frozen=True, eq=False)
class Kinematics:
    """Segment kinematics at ``T`` sample times, world frame unless the name says body.

    ``times_ns (T,)`` int64 on the source track's clock; ``orientations (T, S, 4)`` xyzw
    segment-to-world; ``positions``, ``velocity``, ``acceleration (T, S, 3)`` m, m/s, m/s^2;
    ``angular_velocity_world`` / ``_body`` ``(T, S, 3)`` rad/s; ``angular_acceleration_world`` /
    ``_body`` ``(T, S, 3)`` rad/s^2.
    """

    segment_names: tuple[str, ...]
    times_ns: np.ndarray
    orientations: np.ndarray
    positions: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray
    angular_velocity_world: np.ndarray
    angular_velocity_body: np.ndarray
    angular_acceleration_world: np.ndarray
    angular_acceleration_body: np.ndarray

    def __post_init__(self):
        for name in ("times_ns", *_PER_SEGMENT):
            getattr(self, name).setflags(write=False)

    @property
    def num_samples(self) -> int:
        return self.times_ns.shape[0]

    def select(self, segments) -> "Kinematics":
        """The same kinematics restricted to (and reordered as) segment indices ``segments``."""
        idx = np.asarray(segments, dtype=np.int64)
        arrays = {name: getattr(self, name)[:, idx] for name in _PER_SEGMENT}
        return Kinematics(segment_names=tuple(self.segment_names[i] for i in idx), times_ns=self.times_ns, **arrays)

    def rotations(self, segment: int) -> Rotation:
        """Orientations of segment index ``segment`` as one scipy ``Rotation`` of length ``T``."""
        return Rotation.from_quat(self.orientations[:, segment])

    def point(self, segment: int, offset) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position, velocity and acceleration ``(T, 3)`` (world; m, m/s, m/s^2) of a point fixed at
        ``offset (3,)`` metres in the frame of segment index ``segment``:
        ``p + R r``, ``v + w x R r``, ``a + dw/dt x R r + w x (w x R r)``."""
        r = self.rotations(segment).apply(np.asarray(offset, dtype=np.float64))
        w = self.angular_velocity_world[:, segment]
        dw = self.angular_acceleration_world[:, segment]
        p = self.positions[:, segment] + r
        v = self.velocity[:, segment] + np.cross(w, r)
        a = self.acceleration[:, segment] + np.cross(dw, r) + np.cross(w, np.cross(w, r))
        return p, v, a


class KinematicSpline:
    """Splines through every segment of a ground-truth track; evaluate with :meth:`evaluate`.

    The track must be fully valid (ground truth has no gaps) and have at least two frames with
    strictly increasing ``device_time_ns``. The track is only read, never modified. Inside the
    track the splines follow smooth motion closely (at 60 fps, angular rates to ~1e-5 rad/s);
    over the first and last few frames the not-a-knot end conditions cost some accuracy in the
    derivatives (~1e-2 rad/s, ~1e-2 m/s^2).
    """

    def __init__(self, track: SkeletonTrack):
        if not isinstance(track, SkeletonTrack):
            raise TypeError(f"expected a SkeletonTrack, got {type(track).__name__}")
        if track.num_frames < 2:
            raise ValueError(f"need at least 2 frames to spline a track, got {track.num_frames}")
        if not (track.orientation_valid.all() and track.position_valid.all()):
            raise ValueError("ground truth must be valid everywhere; this track has invalid samples")
        t_ns = track.device_time_ns
        if np.any(np.diff(t_ns) <= 0):
            raise ValueError("device_time_ns must increase strictly to spline a track")
        self.track = track
        self.segment_names = track.segment_names
        self.t0_ns = int(t_ns[0])
        self.t1_ns = int(t_ns[-1])
        t = (t_ns - self.t0_ns) * 1e-9
        S = len(self.segment_names)
        self._pos = CubicSpline(t, track.positions.reshape(len(t), S * 3), axis=0)
        self._vel = self._pos.derivative(1)
        self._acc = self._pos.derivative(2)
        self._rot = [RotationSpline(t, Rotation.from_quat(track.orientations[:, s])) for s in range(S)]

    @property
    def duration_s(self) -> float:
        return (self.t1_ns - self.t0_ns) * 1e-9

    def evaluate(self, times_ns) -> Kinematics:
        """Kinematics at ``times_ns (T,)`` (int or float ns on the track's clock, inside the track)."""
        times_ns = np.atleast_1d(np.asarray(times_ns))
        if times_ns.ndim != 1:
            raise ValueError(f"times_ns must be 1-D, got shape {times_ns.shape}")
        lo, hi = self.t0_ns - _EDGE_SLACK_NS, self.t1_ns + _EDGE_SLACK_NS
        if times_ns.size and (times_ns.min() < lo or times_ns.max() > hi):
            raise ValueError(
                f"times [{times_ns.min()}, {times_ns.max()}] ns fall outside the track "
                f"[{self.t0_ns}, {self.t1_ns}] ns; splines are not extrapolated"
            )
        t = np.clip((times_ns.astype(np.float64) - self.t0_ns) * 1e-9, 0.0, self.duration_s)
        T, S = t.shape[0], len(self.segment_names)
        quat = np.empty((T, S, 4))
        w_body = np.empty((T, S, 3))
        dw_body = np.empty((T, S, 3))
        for s, spline in enumerate(self._rot):
            quat[:, s] = spline(t).as_quat()
            w_body[:, s] = spline(t, 1)
            dw_body[:, s] = spline(t, 2)
        rot = Rotation.from_quat(quat.reshape(-1, 4))
        w_world = rot.apply(w_body.reshape(-1, 3)).reshape(T, S, 3)
        dw_world = rot.apply(dw_body.reshape(-1, 3)).reshape(T, S, 3)
        return Kinematics(
            segment_names=self.segment_names,
            times_ns=np.round(times_ns).astype(np.int64),
            orientations=quat,
            positions=self._pos(t).reshape(T, S, 3),
            velocity=self._vel(t).reshape(T, S, 3),
            acceleration=self._acc(t).reshape(T, S, 3),
            angular_velocity_world=w_world,
            angular_velocity_body=w_body,
            angular_acceleration_world=dw_world,
            angular_acceleration_body=dw_body,
        )


def as_spline(track: SkeletonTrack | KinematicSpline) -> KinematicSpline:
    """``track`` itself if it is already a :class:`KinematicSpline`, else a new spline through it."""
    return track if isinstance(track, KinematicSpline) else KinematicSpline(track)


def sample_times_ns(t0_ns: int, t1_ns: int, rate_hz: float) -> np.ndarray:
    """``t0_ns + round(k * 1e9 / rate_hz)`` for every ``k`` that stays ``<= t1_ns``; int64 ``(T,)``."""
    if not rate_hz > 0:
        raise ValueError(f"rate_hz must be positive, got {rate_hz}")
    n = int(np.floor((t1_ns - t0_ns) * 1e-9 * rate_hz + 1e-9)) + 1
    return t0_ns + np.round(np.arange(n) * (1e9 / rate_hz)).astype(np.int64)


def resample(track: SkeletonTrack | KinematicSpline, rate_hz: float, t0_ns: int | None = None,
             duration_s: float | None = None) -> Kinematics:  # fmt: skip
    """Kinematics of ``track`` at ``rate_hz`` from ``t0_ns`` (default: its first frame) for
    ``duration_s`` seconds (default: to its last frame), on the track's own clock."""
    spline = as_spline(track)
    t0 = spline.t0_ns if t0_ns is None else int(t0_ns)
    t1 = spline.t1_ns if duration_s is None else t0 + int(round(duration_s * 1e9))
    return spline.evaluate(sample_times_ns(t0, t1, rate_hz))


# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class DeviceClock:
    """How a device and the host stamp a sample taken at ground-truth time ``t`` (seconds on the
    scene clock, the time axis of the ground-truth track).

    * device clock: ``device(t) = offset_s + (1 + drift_ppm * 1e-6) * t`` — a constant offset and
      a linear drift (a crystal off its nominal frequency);
    * host clock (monotonic receive time): ``host(t) = host_offset_s + t + latency_s + J``, with
      ``J`` exponential with mean ``jitter_s`` (queueing and network delay: always positive), made
      non-decreasing in the order of arrival.

    A device sampling at ``rate_hz`` takes sample ``k`` when its own clock has advanced by
    ``k / rate_hz``, so a drifting device samples at slightly irregular scene times.
    """

    offset_s: float = 0.0
    drift_ppm: float = 0.0
    host_offset_s: float = 0.0
    latency_s: float = 0.002
    jitter_s: float = 0.0005

    def __post_init__(self):
        if self.latency_s < 0 or self.jitter_s < 0:
            raise ValueError("latency_s and jitter_s must be non-negative")
        if not -1e5 < self.drift_ppm < 1e5:
            raise ValueError(f"drift_ppm {self.drift_ppm} is not a clock drift")

    @property
    def rate(self) -> float:
        """Device seconds per scene second."""
        return 1.0 + self.drift_ppm * 1e-6

    def device_time_ns(self, true_ns) -> np.ndarray:
        """Device clock reading (int64 ns) at scene times ``true_ns``."""
        true_ns = np.asarray(true_ns, dtype=np.float64)
        return np.round(self.offset_s * 1e9 + self.rate * true_ns).astype(np.int64)

    def true_time_ns(self, device_ns) -> np.ndarray:
        """Scene time (float ns) at which the device clock reads ``device_ns``."""
        return (np.asarray(device_ns, dtype=np.float64) - self.offset_s * 1e9) / self.rate

    def sample_times(self, t0_ns: int, t1_ns: int, rate_hz: float) -> tuple[np.ndarray, np.ndarray]:
        """Samples of a device running at ``rate_hz`` on its own clock, from scene time ``t0_ns``
        until no later than ``t1_ns``: ``(device_ns int64 (T,), true_ns float (T,))``."""
        if not rate_hz > 0:
            raise ValueError(f"rate_hz must be positive, got {rate_hz}")
        d0 = int(self.device_time_ns(t0_ns))
        d1 = float(self.offset_s * 1e9 + self.rate * t1_ns)
        n = int(np.floor((d1 - d0) * 1e-9 * rate_hz + 1e-9)) + 1
        device = d0 + np.round(np.arange(max(n, 0)) * (1e9 / rate_hz)).astype(np.int64)
        true = np.clip(self.true_time_ns(device), t0_ns, t1_ns)
        return device, true

    def host_time_ns(self, true_ns, rng: np.random.Generator) -> np.ndarray:
        """Host receive times (int64 ns, non-decreasing along the last axis, the order of arrival)
        of samples taken at scene times ``true_ns``."""
        true_ns = np.asarray(true_ns, dtype=np.float64)
        delay = self.latency_s + (rng.exponential(self.jitter_s, true_ns.shape) if self.jitter_s > 0 else 0.0)
        host = np.round(self.host_offset_s * 1e9 + true_ns + delay * 1e9).astype(np.int64)
        return np.maximum.accumulate(host, axis=-1) if host.size else host

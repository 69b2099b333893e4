"""Typed samples: what every capture source yields, live or simulated, after decoding.

Decoders are the edge where wire formats become our conventions
(:mod:`dualhuman_builder.conventions`): positions in metres, world frame **Y-up**, quaternions
``(x, y, z, w)``, angles in radians. Each sample carries the device's own timestamp and the host's
monotonic receive time, both int64 nanoseconds; neither is ever dropped.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, eq=False)
class SuitFrame:
    """One MVN character's segment poses at one sample (MVN message type 02).

    ``character``: MVN character (avatar) ID; ``sample_counter``: MVN's sample counter (u32 on the
    wire, unwrapped by the decoder; may skip); ``time_code_ms``: ms since the start of the recording clock (MVN time code);
    ``segment_names (S,)``; ``orientations (S, 4)`` world-frame segment orientations;
    ``positions (S, 3)`` segment origins, metres.
    """

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    segment_names: tuple[str, ...]
    orientations: np.ndarray
    positions: np.ndarray


@dataclass(frozen=True, eq=False)
class TrackerSample:
    """One VIVE-style tracker pose. ``valid`` False means tracking was lost (the pose is then
    meaningless, as real trackers report it: an invalid flag or a jump to the origin).

    ``position (3,)`` metres and ``orientation (4,)`` in the world frame; ``velocity (3,)`` m/s
    and ``angular_velocity (3,)`` rad/s in the world frame.
    """

    serial: str
    valid: bool
    device_time_ns: int
    host_time_ns: int
    position: np.ndarray
    orientation: np.ndarray
    velocity: np.ndarray
    angular_velocity: np.ndarray


@dataclass(frozen=True, eq=False)
class ImuSample:
    """One MTi-style IMU sample (Xbus MTData2 or MTi CAN).

    ``counter``: packet counter (u16, wraps); ``device_time_ns``: SampleTimeFine (10 kHz ticks)
    as ns; ``orientation (4,)``: sensor orientation in the world frame (the MTi's own Z-up earth
    frame converted to Y-up); ``acceleration (3,)`` m/s^2 (specific force, gravity included),
    ``rate_of_turn (3,)`` rad/s and ``magnetic_field (3,)`` arbitrary units, all in the
    **sensor** frame; ``status``: the status word.
    """

    device: str
    counter: int
    device_time_ns: int
    host_time_ns: int
    orientation: np.ndarray
    acceleration: np.ndarray
    rate_of_turn: np.ndarray
    magnetic_field: np.ndarray
    status: int = 0


# ------------------------------------------------------------------ MVN network stream, other types
# Each carries the header of its message: ``character`` (MVN character ID), ``sample_counter``
# (unwrapped, as in SuitFrame), ``time_code_ms`` (ms on MVN's recording clock) and
# ``device_time_ns = time_code_ms * 1_000_000``.


@dataclass(frozen=True, eq=False)
class SuitMeta:
    """MVN character meta data (message type 12): ``name`` as shown in MVN, ``xmid`` (BodyPack /
    Awinda station ID), ``color`` (hex ``RRGGBB``), each "" when not sent; every tag in the order
    sent: ``tags`` and their ``values`` (unknown tags kept)."""

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    name: str
    xmid: str
    color: str
    tags: tuple[str, ...]
    values: tuple[str, ...]


@dataclass(frozen=True, eq=False)
class SuitScale:
    """One MVN scale message (type 13) of the null pose (all segment orientations identity, body
    facing +X), Y-up world metres. MVN sends the segments in one message and the points in
    several more: ``segment_names (S,)`` with ``segment_origins (S, 3)``; points ``point_names
    (P,)``, ``point_segment_ids``, ``point_ids`` (local to the segment) and ``point_flags`` ``(P,)``
    int64, ``point_positions (P, 3)`` relative to the segment origin."""

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    segment_names: tuple[str, ...]
    segment_origins: np.ndarray
    point_names: tuple[str, ...]
    point_segment_ids: np.ndarray
    point_ids: np.ndarray
    point_flags: np.ndarray
    point_positions: np.ndarray


@dataclass(frozen=True, eq=False)
class JointAngles:
    """MVN joint angles (type 20): per joint ``parent_point_ids`` and ``child_point_ids (J,)``
    int64 (``256 * segment ID + local point ID`` of the connection points) and ``angles (J, 3)``,
    rotations about the segment's x, y, z axes in radians (sent in degrees)."""

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    parent_point_ids: np.ndarray
    child_point_ids: np.ndarray
    angles: np.ndarray


@dataclass(frozen=True, eq=False)
class LinearSegmentKinematics:
    """MVN linear segment kinematics (type 21), world frame Y-up: ``segment_names (S,)``,
    ``positions`` m, ``velocities`` m/s and ``accelerations`` m/s^2, each ``(S, 3)``."""

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    segment_names: tuple[str, ...]
    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray


@dataclass(frozen=True, eq=False)
class AngularSegmentKinematics:
    """MVN angular segment kinematics (type 22), world frame Y-up: ``segment_names (S,)``,
    ``orientations (S, 4)`` (x, y, z, w), ``angular_velocities`` rad/s and
    ``angular_accelerations`` rad/s^2, each ``(S, 3)``."""

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    segment_names: tuple[str, ...]
    orientations: np.ndarray
    angular_velocities: np.ndarray
    angular_accelerations: np.ndarray


@dataclass(frozen=True, eq=False)
class CenterOfMass:
    """MVN centre of mass (type 24): ``position (3,)``, m, world frame Y-up."""

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    position: np.ndarray


@dataclass(frozen=True, eq=False)
class SuitTimeCode:
    """MVN time code (type 25), sent with the pose of the same sample: ``text`` ``HH:MM:SS.mmm``
    and ``time_of_day_ms``, its value in ms (hours wrap at 24)."""

    character: int
    sample_counter: int
    time_code_ms: int
    device_time_ns: int
    host_time_ns: int
    text: str
    time_of_day_ms: int

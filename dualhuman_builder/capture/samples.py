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

    ``character``: MVN character (avatar) ID; ``sample_counter``: MVN's sample counter (u32, may
    skip); ``time_code_ms``: ms since the start of the recording clock (MVN time code);
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

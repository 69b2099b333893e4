"""Xsens MTi-600 CAN frames (``shared/reference/capture-protocols.md``, from the ``xsens.dbc`` of
``jiminghe/Xsens_MTi_CAN_ROS_Driver``), as python-can :class:`can.Message` objects.

Standard 11-bit identifiers; every signal **Motorola (big-endian)**. One sample becomes, in this
order (SampleTime first, so a receiver can group the frames of one sample):

==========  ======================  ====  =========================================================
CAN id      content                 DLC   encoding
==========  ======================  ====  =========================================================
0x05        SampleTime              4     u32 microseconds of ``device_time_ns`` (rounded, mod 2**32)
0x06        GroupCounter            2     u16 packet counter (wraps)
0x11        StatusWord              4     u32 status word
0x21        Quaternion q0..q3       8     4 x int16, scale 2**-15; (w, x, y, z), sensor to the
                                          MTi's Z-up earth frame (inverse of ``ZUP_TO_YUP``)
0x32        RateOfTurn x, y, z      6     3 x int16, scale 2**-9 rad/s, sensor frame
0x34        Acceleration x, y, z    6     3 x int16, scale 2**-8 m/s^2, sensor frame
0x35        FreeAcceleration        6     3 x int16, scale 2**-8 m/s^2, Z-up earth frame
0x41        MagneticField x, y, z   6     3 x int16, scale 2**-10 a.u., sensor frame
==========  ======================  ====  =========================================================

**Saturation**: an int16 signal holds ``[-32768, 32767] * scale``; values beyond are clamped to
the nearest end (as the device clips), e.g. a quaternion component of exactly 1.0 is sent as
32767 (0.99997), accelerations beyond +-128 m/s^2 and rates beyond +-64 rad/s are clipped.
Values are rounded to the nearest step. Free acceleration is derived, as the MTi does: the
specific force rotated to the earth frame with gravity (9.80665 m/s^2) removed.
"""

from __future__ import annotations

import struct
from enum import IntEnum

import can
import numpy as np
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.wire import check_finite, check_unit_quaternions, to_zup_wxyz
from dualhuman_builder.conventions import GRAVITY, yup_to_zup_points


class CanId(IntEnum):
    """Standard (11-bit) identifiers of the MTi-600 frames encoded here."""

    SAMPLE_TIME = 0x05
    GROUP_COUNTER = 0x06
    STATUS_WORD = 0x11
    QUATERNION = 0x21
    EULER = 0x22
    RATE_OF_TURN = 0x32
    ACCELERATION = 0x34
    FREE_ACCELERATION = 0x35
    MAGNETIC_FIELD = 0x41
    TEMPERATURE = 0x51


#: Value of one int16 step of each scaled signal (SI units; magnetic field arbitrary units).
SCALES = {
    CanId.QUATERNION: 2.0**-15,
    CanId.EULER: 2.0**-7,  # degrees
    CanId.RATE_OF_TURN: 2.0**-9,
    CanId.ACCELERATION: 2.0**-8,
    CanId.FREE_ACCELERATION: 2.0**-8,
    CanId.MAGNETIC_FIELD: 2.0**-10,
    CanId.TEMPERATURE: 2.0**-8,  # degrees Celsius
}
#: Frames of one sample, in the order :func:`encode_can` returns them.
FRAME_ORDER = (CanId.SAMPLE_TIME, CanId.GROUP_COUNTER, CanId.STATUS_WORD, CanId.QUATERNION,
               CanId.RATE_OF_TURN, CanId.ACCELERATION, CanId.FREE_ACCELERATION, CanId.MAGNETIC_FIELD)
INT16_MIN, INT16_MAX = -32768, 32767


def to_int16(values, scale: float) -> np.ndarray:
    """Physical values -> int16 counts: ``round(v / scale)`` clamped to [-32768, 32767]."""
    counts = np.rint(np.asarray(values, dtype=np.float64) / scale)
    return np.clip(counts, INT16_MIN, INT16_MAX).astype(np.int64)


def free_acceleration_zup(sample: ImuSample) -> np.ndarray:
    """Free acceleration ``(3,)`` m/s^2 in the MTi's Z-up earth frame: ``R f + g`` in our world,
    rotated to Z-up (``f`` the specific force in the sensor frame, ``g`` gravity)."""
    # copies: scipy rejects read-only buffers, and simulators hand out frozen arrays
    r = Rotation.from_quat(np.array(sample.orientation, dtype=np.float64))  # xyzw
    return yup_to_zup_points(r.apply(np.array(sample.acceleration, dtype=np.float64)) + GRAVITY)


def _msg(can_id: int, data: bytes, timestamp: float) -> can.Message:
    return can.Message(arbitration_id=int(can_id), data=data, is_extended_id=False, timestamp=timestamp)


def encode_can(sample: ImuSample) -> list[can.Message]:
    """The frames of one sample (see the module table), ``timestamp`` = device time in seconds.

    Raises ``ValueError`` on non-finite values or a non-unit orientation; clamps out-of-range
    signals (see the module docstring).
    """
    check_unit_quaternions(sample.orientation, f"orientation of IMU {sample.device!r}")
    acc = check_finite(sample.acceleration, "acceleration")
    gyr = check_finite(sample.rate_of_turn, "rate of turn")
    mag = check_finite(sample.magnetic_field, "magnetic field")
    t = sample.device_time_ns / 1e9
    us = ((int(sample.device_time_ns) + 500) // 1000) & 0xFFFFFFFF
    i16 = struct.Struct(">3h")
    quat = to_int16(to_zup_wxyz(sample.orientation), SCALES[CanId.QUATERNION])
    free = to_int16(free_acceleration_zup(sample), SCALES[CanId.FREE_ACCELERATION])
    return [
        _msg(CanId.SAMPLE_TIME, struct.pack(">I", us), t),
        _msg(CanId.GROUP_COUNTER, struct.pack(">H", int(sample.counter) & 0xFFFF), t),
        _msg(CanId.STATUS_WORD, struct.pack(">I", int(sample.status) & 0xFFFFFFFF), t),
        _msg(CanId.QUATERNION, struct.pack(">4h", *quat), t),
        _msg(CanId.RATE_OF_TURN, i16.pack(*to_int16(gyr, SCALES[CanId.RATE_OF_TURN])), t),
        _msg(CanId.ACCELERATION, i16.pack(*to_int16(acc, SCALES[CanId.ACCELERATION])), t),
        _msg(CanId.FREE_ACCELERATION, i16.pack(*free), t),
        _msg(CanId.MAGNETIC_FIELD, i16.pack(*to_int16(mag, SCALES[CanId.MAGNETIC_FIELD])), t),
    ]

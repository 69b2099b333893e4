"""Xsens MTi-600 CAN frames (signals as in ``config/xsens.dbc`` of
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

Decoding (:func:`decode_can_signals`) reads every ID of :class:`CanId` — also Euler (0x22, 3 x
int16 roll, pitch, yaw, 2**-7 degrees, DLC 6) and Temperature (0x51, int16, 2**-8 degrees
Celsius, DLC 2), which the encoder does not write — with the DLCs in :data:`DLC`.

A received frame travels as the 16-byte SocketCAN ``struct can_frame`` (``'<IB3x8s'``: can_id with
the flags :data:`CAN_EFF_FLAG` / :data:`CAN_RTR_FLAG` / :data:`CAN_ERR_FLAG`, dlc, data padded
with zeros to 8 bytes), pinned little-endian here: :func:`pack_can_frame`, :func:`unpack_can_frame`.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import NamedTuple

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


# ----------------------------------------------------------------------------------- decoding
#: Data length of each frame, bytes.
DLC = {CanId.SAMPLE_TIME: 4, CanId.GROUP_COUNTER: 2, CanId.STATUS_WORD: 4, CanId.QUATERNION: 8, CanId.EULER: 6,
       CanId.RATE_OF_TURN: 6, CanId.ACCELERATION: 6, CanId.FREE_ACCELERATION: 6, CanId.MAGNETIC_FIELD: 6,
       CanId.TEMPERATURE: 2}  # fmt: skip
_SIGNALS = {CanId.SAMPLE_TIME: struct.Struct(">I"), CanId.GROUP_COUNTER: struct.Struct(">H"),
            CanId.STATUS_WORD: struct.Struct(">I"), CanId.QUATERNION: struct.Struct(">4h"),
            CanId.TEMPERATURE: struct.Struct(">h")}  # fmt: skip
_I16X3 = struct.Struct(">3h")
#: (unpack, scale) of each ID; scale None: integers as sent. Euler's scale gives radians.
_DECODE = {int(i): (_SIGNALS.get(i, _I16X3).unpack, None if i not in SCALES else SCALES[i]) for i in DLC}
_DECODE[int(CanId.EULER)] = (_I16X3.unpack, SCALES[CanId.EULER] * np.pi / 180.0)


def decode_can_signals(can_id: int, data: bytes) -> tuple:
    """The values of one frame's data (``len(data)`` must be ``DLC[can_id]``): SampleTime
    ``(us,)``, GroupCounter ``(counter,)``, StatusWord ``(word,)`` as integers; Quaternion
    ``(w, x, y, z)`` (Z-up earth, not normalised); RateOfTurn rad/s, Acceleration and
    FreeAcceleration m/s^2, MagneticField a.u., all ``(x, y, z)``; Euler ``(roll, pitch, yaw)``
    in **radians**; Temperature ``(celsius,)``. Frames as sent: sensor frame or Z-up earth.
    ``KeyError`` for an ID not in :data:`DLC`, ``struct.error`` for a wrong length."""
    unpack, scale = _DECODE[can_id]
    values = unpack(data)
    return values if scale is None else tuple(v * scale for v in values)


CAN_EFF_FLAG = 0x80000000
CAN_RTR_FLAG = 0x40000000
CAN_ERR_FLAG = 0x20000000
CAN_SFF_MASK = 0x000007FF
CAN_EFF_MASK = 0x1FFFFFFF
#: SocketCAN ``struct can_frame``: can_id (u32 with flags), len (u8), 3 pad bytes, data[8].
CAN_FRAME = struct.Struct("<IB3x8s")


class CanFrame(NamedTuple):
    """One classic CAN frame as :func:`unpack_can_frame` reads it. ``arbitration_id`` without
    the flags (the error class bits for an error frame); ``data``: the first ``dlc`` bytes."""

    arbitration_id: int
    is_extended_id: bool
    is_remote_frame: bool
    is_error_frame: bool
    dlc: int
    data: bytes


def pack_can_frame(msg: can.Message) -> bytes:
    """``msg`` as a 16-byte SocketCAN ``struct can_frame`` (little-endian ``'<IB3x8s'``).
    ``ValueError`` for a CAN FD frame or data longer than 8 bytes (not a classic frame)."""
    data = bytes(msg.data or b"")
    if msg.is_fd or len(data) > 8 or not 0 <= msg.dlc <= 8:
        raise ValueError(f"CAN id 0x{msg.arbitration_id:X}: not a classic CAN frame (FD or {len(data)} data bytes)")
    can_id = msg.arbitration_id & (CAN_EFF_MASK if msg.is_extended_id else CAN_SFF_MASK)
    if msg.is_extended_id:
        can_id |= CAN_EFF_FLAG
    if msg.is_remote_frame:
        can_id |= CAN_RTR_FLAG
    if msg.is_error_frame:
        can_id = (msg.arbitration_id & CAN_EFF_MASK) | CAN_ERR_FLAG
    return CAN_FRAME.pack(can_id, msg.dlc if msg.is_remote_frame else len(data), data)


def unpack_can_frame(data: bytes) -> CanFrame:
    """Inverse of :func:`pack_can_frame`. ``ValueError`` unless ``data`` is 16 bytes with a
    length field of at most 8."""
    if len(data) != CAN_FRAME.size:
        raise ValueError(f"a SocketCAN can_frame has {CAN_FRAME.size} bytes, got {len(data)}")
    can_id, dlc, payload = CAN_FRAME.unpack(data)
    if dlc > 8:
        raise ValueError(f"can_frame length field {dlc} > 8")
    extended = bool(can_id & CAN_EFF_FLAG)
    remote = bool(can_id & CAN_RTR_FLAG)
    error = bool(can_id & CAN_ERR_FLAG)
    ident = can_id & (CAN_EFF_MASK if extended or error else CAN_SFF_MASK)
    return CanFrame(ident, extended, remote, error, dlc, b"" if remote else payload[:dlc])

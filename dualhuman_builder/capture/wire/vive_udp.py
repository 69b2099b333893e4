"""Our VIVE tracker bridge datagram: the format an OpenVR or libsurvive bridge sends to
``vive+udp://:8051``, one tracker pose per UDP datagram.

triad_openvr's own emitter packs in native byte order without a timestamp; ours pins
**little-endian**, fixed size, 128 bytes, :data:`TRACKER_DATAGRAM` ``'<4sBBH32sq3d4d3f3f'``:

======  ====  ====================================================================================
offset  size  field
======  ====  ====================================================================================
0       4     magic ``b"DHVT"``
4       1     format version, :data:`VERSION` (1)
5       1     flags: bit 0 pose valid (OpenVR ``bPoseIsValid``), bit 1 device connected
              (``bDeviceIsConnected``); other bits zero
6       2     reserved, zero
8       32    tracker serial number, ASCII, NUL-padded (a 32-character serial has no NUL)
40      8     device timestamp, i64 ns (OpenVR exposes none: the bridge stamps each pose with its
              own monotonic clock when it reads it; libsurvive's 48 MHz timecode converted to ns)
48      24    position x, y, z, f64 metres
72      32    orientation quaternion **(x, y, z, w)**, f64 (scalar last, as everywhere in our code)
104     12    linear velocity x, y, z, f32 m/s
116     12    angular velocity x, y, z, f32 rad/s
======  ====  ====================================================================================

Frame: our world, right-handed, **+Y up**, metres. OpenVR's standing universe is already Y-up
right-handed, so an OpenVR bridge sends its values as they are; a libsurvive (Z-up) bridge rotates
them with :data:`dualhuman_builder.conventions.ZUP_TO_YUP` first. A pose that is not valid is sent
with the valid flag clear; its non-finite values, if any, are sent as 0 (as OpenVR reports a lost
pose), so a datagram never carries NaN.

:func:`encode_tracker` writes a datagram, :func:`decode_tracker` reads one back bit for bit (or
raises :class:`ViveFormatError` naming the counter the bad datagram falls under); the stream
logic (duplicates, order, tracking loss, liveness) is
:class:`~dualhuman_builder.capture.vive_udp.ViveUdpDecoder`'s.
"""

from __future__ import annotations

import math
import struct

import numpy as np

from dualhuman_builder.capture.samples import TrackerSample
from dualhuman_builder.capture.wire import check_finite, check_unit_quaternions

#: UDP port the bridge sends to (triad_openvr's, reused).
DEFAULT_PORT = 8051
MAGIC = b"DHVT"
VERSION = 1
#: The whole datagram: magic, version, flags, reserved, serial, time (ns), position (3 f64),
#: quaternion x, y, z, w (4 f64), linear velocity (3 f32), angular velocity (3 f32).
TRACKER_DATAGRAM = struct.Struct("<4sBBH32sq3d4d3f3f")
SERIAL_SIZE = 32
FLAG_POSE_VALID = 0x01
FLAG_CONNECTED = 0x02


def encode_tracker(sample: TrackerSample, *, connected: bool = True) -> bytes:
    """One :class:`TrackerSample` as a 128-byte bridge datagram (see the module docstring).

    Raises ``ValueError`` for a serial that is not ASCII or longer than 32 bytes, a device time
    outside int64, and, for a valid pose, non-finite values or a non-unit quaternion.
    """
    try:
        serial = sample.serial.encode("ascii")
    except UnicodeEncodeError:
        raise ValueError(f"tracker serial {sample.serial!r} is not ASCII") from None
    if not serial or len(serial) > SERIAL_SIZE or b"\0" in serial:
        raise ValueError(f"tracker serial {sample.serial!r} must be 1..{SERIAL_SIZE} ASCII characters without NUL")
    if not -(2**63) <= sample.device_time_ns < 2**63:
        raise ValueError(f"device time must fit in int64 ns, got {sample.device_time_ns}")
    fields = [sample.position, sample.orientation, sample.velocity, sample.angular_velocity]
    if sample.valid:
        names = ("position", "orientation", "velocity", "angular velocity")
        fields = [check_finite(v, f"{n} of tracker {sample.serial}") for v, n in zip(fields, names)]
        check_unit_quaternions(fields[1], f"orientation of tracker {sample.serial}")
    else:
        fields = [np.nan_to_num(np.asarray(v, dtype=np.float64), nan=0.0, posinf=0.0, neginf=0.0) for v in fields]
    pos, quat, vel, ang = fields
    if pos.shape != (3,) or quat.shape != (4,) or vel.shape != (3,) or ang.shape != (3,):
        raise ValueError("tracker position, velocity and angular velocity must be (3,), orientation (4,)")
    flags = (FLAG_POSE_VALID if sample.valid else 0) | (FLAG_CONNECTED if connected else 0)
    return TRACKER_DATAGRAM.pack(MAGIC, VERSION, flags, 0, serial, int(sample.device_time_ns),
                                 *pos, *quat, *vel, *ang)


# ----------------------------------------------------------------------------------- decoding
class ViveFormatError(ValueError):
    """A datagram that is not a well-formed tracker datagram. ``counter`` names the decoder
    counter it falls under: ``truncated`` (shorter than 128 bytes), ``bad_length`` (longer),
    ``bad_magic``, ``bad_version``, ``bad_field`` (reserved flag bits or reserved bytes set, a
    serial that is empty, not ASCII or has bytes after its NUL padding starts), ``bad_pose`` (a
    pose flagged valid with NaN/inf or a quaternion whose norm is off 1 by more than 1e-3)."""

    def __init__(self, counter: str, message: str):
        super().__init__(message)
        self.counter = counter


def decode_tracker(data: bytes, host_time_ns: int) -> TrackerSample:
    """Inverse of :func:`encode_tracker`: one 128-byte datagram -> :class:`TrackerSample`.

    ``valid`` is the datagram's pose-valid flag as sent (the device-connected flag is not part of
    the sample: read it with :func:`datagram_connected`). Positions and quaternions come back as
    the exact float64 sent, velocities as the float32 sent (widened to float64); all arrays are read-only. ``host_time_ns``: when the datagram arrived
    (int ns). Raises :class:`ViveFormatError` (with the counter name) for anything malformed;
    the payload of a pose flagged invalid is not checked (it is meaningless by definition).
    """
    n = len(data)
    if n != TRACKER_DATAGRAM.size:
        kind = "truncated" if n < TRACKER_DATAGRAM.size else "bad_length"
        raise ViveFormatError(kind, f"tracker datagram has {n} bytes, expected {TRACKER_DATAGRAM.size}")
    magic, version, flags, reserved, raw_serial, t_ns, *values = TRACKER_DATAGRAM.unpack(data)
    if magic != MAGIC:
        raise ViveFormatError("bad_magic", f"tracker datagram starts with {magic!r}, expected {MAGIC!r}")
    if version != VERSION:
        raise ViveFormatError("bad_version", f"tracker datagram version {version}, this decoder reads {VERSION}")
    if flags & ~(FLAG_POSE_VALID | FLAG_CONNECTED) or reserved:
        raise ViveFormatError("bad_field", f"reserved bits set (flags 0x{flags:02x}, reserved 0x{reserved:04x})")
    name = raw_serial.rstrip(b"\0")
    if not name or b"\0" in name or not name.isascii():
        raise ViveFormatError("bad_field", f"bad tracker serial field {raw_serial!r}")
    valid = bool(flags & FLAG_POSE_VALID)
    serial = name.decode("ascii")
    if valid:
        # plain floats: numpy's per-call overhead dominates on 13 values (this runs 3,000 times a second)
        if not all(map(math.isfinite, values)):
            raise ViveFormatError("bad_pose", f"valid pose of tracker {serial} holds NaN or infinite values")
        qx, qy, qz, qw = values[3:7]
        # a corrupted exponent can make a component huge: bound it before squaring (no overflow)
        big = max(abs(qx), abs(qy), abs(qz), abs(qw))
        norm = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw) if big <= 2.0 else big
        if abs(norm - 1.0) > 1e-3:
            raise ViveFormatError("bad_pose", f"valid pose of tracker {serial} has a quaternion of norm {norm:.6g}")
    arr = np.array(values, dtype=np.float64)
    arr.setflags(write=False)
    pos, quat, vel, ang = arr[0:3], arr[3:7], arr[7:10], arr[10:13]
    return TrackerSample(serial=serial, valid=valid, device_time_ns=int(t_ns), host_time_ns=int(host_time_ns),
                         position=pos, orientation=quat, velocity=vel, angular_velocity=ang)  # fmt: skip


def datagram_connected(data: bytes) -> bool:
    """The device-connected flag (bit 1 of byte 5) of a datagram :func:`decode_tracker` accepted."""
    return len(data) > 5 and bool(data[5] & FLAG_CONNECTED)

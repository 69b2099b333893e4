"""VIVE tracker IMU over USB HID: the report a tracker plugged in by cable sends on its HID
interrupt endpoint (layout and scales as in OpenHMD's ``src/drv_htc_vive/vive.h``).

**The pose is not in the HID stream**: a tracker's pose needs the lighthouse solver (OpenVR or
libsurvive); over raw USB we read only its IMU — acceleration and angular rate.

Report :data:`IMU_REPORT_ID` (0x20), exactly :data:`REPORT_SIZE` = 52 bytes, little-endian:

======  ====  ====================================================================================
offset  size  field
======  ====  ====================================================================================
0       1     report id, 0x20
1       17    sample 0: ``int16 acc[3]; int16 gyro[3]; u32 time_ticks; u8 seq``
18      17    sample 1
35      17    sample 2
======  ====  ====================================================================================

Units: ``acc`` counts x :data:`ACC_SCALE` (9.80665/4096) m/s^2 (specific force, gravity
included), ``gyro`` counts x :data:`GYRO_SCALE` ((1/32.768) deg/s in rad/s), both in the IMU's
own axes, uncalibrated (the per-device bias and scale of the tracker's configuration blob are not
applied). ``time_ticks``: the tracker's 48 MHz clock (:data:`TICK_HZ`), u32, wrapping every
2^32 / 48e6 = 89.48 s. ``seq``: u8, +1 per IMU sample. The three slots are a ring of the latest
samples, so consecutive reports repeat samples and the slots need not be in time order: ``seq``
tells new samples from already-seen ones (:class:`~dualhuman_builder.capture.vive_usb.ViveUsbDecoder`).

USB ids: Valve vendor :data:`VALVE_VENDOR_ID` 0x28de; :data:`PRODUCTS` tracker 0x2022, tracker
v2 0x2300, Watchman dongle 0x2101.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import Sequence

VALVE_VENDOR_ID = 0x28DE
#: Product id -> name of the Valve devices the USB source opens.
PRODUCTS = {0x2022: "VIVE Tracker", 0x2300: "VIVE Tracker v2", 0x2101: "Watchman dongle"}
IMU_REPORT_ID = 0x20
SAMPLES_PER_REPORT = 3
#: One slot: acc x, y, z, gyro x, y, z (int16), time ticks (u32), seq (u8).
SAMPLE = struct.Struct("<6hIB")
REPORT_SIZE = 1 + SAMPLES_PER_REPORT * SAMPLE.size  # 52
#: m/s^2 per accelerometer count.
ACC_SCALE = 9.80665 / 4096.0
#: rad/s per gyroscope count.
GYRO_SCALE = (1.0 / 32.768) * math.pi / 180.0
#: Tracker clock, ticks per second.
TICK_HZ = 48_000_000


@dataclass(frozen=True)
class HidImuSample:
    """One IMU slot as the tracker sends it: raw ``acc (3,)`` and ``gyro (3,)`` int16 counts,
    ``time_ticks`` (u32, 48 MHz), ``seq`` (u8)."""

    acc: tuple[int, int, int]
    gyro: tuple[int, int, int]
    time_ticks: int
    seq: int


class ViveHidError(ValueError):
    """A report that is not an IMU report. ``counter``: ``unknown_id`` (another report id: not an
    IMU report), ``truncated`` (fewer than 52 bytes), ``bad_length`` (more than 52 bytes)."""

    def __init__(self, counter: str, message: str):
        super().__init__(message)
        self.counter = counter


def encode_imu_report(samples: Sequence[HidImuSample]) -> bytes:
    """The 52-byte IMU report of exactly three slots, in the order given. ``ValueError`` for a
    count other than 3 or a field out of its integer range."""
    if len(samples) != SAMPLES_PER_REPORT:
        raise ValueError(f"an IMU report holds {SAMPLES_PER_REPORT} samples, got {len(samples)}")
    out = bytearray([IMU_REPORT_ID])
    for s in samples:
        values = (*s.acc, *s.gyro)
        if len(values) != 6 or not all(-32768 <= int(v) <= 32767 for v in values):
            raise ValueError(f"acc and gyro must be 3 int16 each, got {s.acc}, {s.gyro}")
        if not 0 <= s.time_ticks < 2**32 or not 0 <= s.seq < 256:
            raise ValueError(f"time_ticks must be u32 and seq u8, got {s.time_ticks}, {s.seq}")
        out += SAMPLE.pack(*(int(v) for v in values), int(s.time_ticks), int(s.seq))
    return bytes(out)


def decode_imu_report(data: bytes) -> tuple[HidImuSample, HidImuSample, HidImuSample]:
    """The three slots of an IMU report, in report order. Checks the report id first (another
    report of the device is ``unknown_id``), then the size (exactly 52 bytes); raises
    :class:`ViveHidError`."""
    if not data:
        raise ViveHidError("truncated", "empty HID report")
    if data[0] != IMU_REPORT_ID:
        raise ViveHidError("unknown_id", f"HID report id 0x{data[0]:02x} is not the IMU report 0x{IMU_REPORT_ID:02x}")
    if len(data) != REPORT_SIZE:
        kind = "truncated" if len(data) < REPORT_SIZE else "bad_length"
        raise ViveHidError(kind, f"IMU report has {len(data)} bytes, expected {REPORT_SIZE}")
    out = []
    for k in range(SAMPLES_PER_REPORT):
        *v, ticks, seq = SAMPLE.unpack_from(data, 1 + k * SAMPLE.size)
        out.append(HidImuSample(tuple(v[:3]), tuple(v[3:]), ticks, seq))
    return tuple(out)


def counts_from_si(acceleration, rate_of_turn) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """Acceleration (m/s^2) and angular rate (rad/s), sensor frame, as the int16 counts a tracker
    would send: rounded to the nearest count and clipped to the int16 range (as a saturated
    sensor reads)."""

    def counts(v, scale):
        return tuple(int(min(32767, max(-32768, round(float(x) / scale)))) for x in v)

    return counts(acceleration, ACC_SCALE), counts(rate_of_turn, GYRO_SCALE)


def ticks_to_ns(ticks: int) -> int:
    """An unwrapped 48 MHz tick count as int ns (floor): ``ticks * 125 // 6``."""
    return ticks * 125 // 6

"""Xsens MTi "Xbus" serial protocol: frames, MTData2 records, and a simulated device's replies.

Frame (``shared/reference/capture-protocols.md``, from ``ethz-asl/ethzasl_xsens_driver``)::

    FA  FF  MID  LEN  [FF LENH LENL when the data is longer than 254 bytes]  DATA  CS

``FA`` is the preamble, ``FF`` the bus ID of the master device, ``LEN`` the data length (the
extended form puts 0xFF in ``LEN`` and the length as a big-endian u16 after it). ``CS`` makes the
sum of every byte after the preamble, checksum included, 0 mod 256.

MTData2 (MID 0x36) data is a sequence of records ``'!HB'`` (data ID, size) + payload, big-endian.
The low two bits of a data ID select the precision (0: float32, 3: float64); this encoder writes
float32. Records written (:class:`XDI`): PacketCounter ``!H``, SampleTimeFine ``!L`` (10 kHz
ticks, rounded from ``device_time_ns``, modulo 2**32 like the device's counter, so a simulated clock
that reads negative wraps too), Quaternion ``!4f`` (w, x, y, z:
sensor to the MTi's **Z-up** earth frame, converted from our Y-up world with the inverse of
``ZUP_TO_YUP``), Acceleration, RateOfTurn and MagneticField ``!3f`` (sensor frame, unchanged),
StatusWord ``!L``.

:class:`SimulatedMti` is the device's side of the configuration dialogue (WakeUp, GoToConfig,
SetOutputConfiguration, GoToMeasurement, ReqDID); every accepted message is acknowledged with
MID + 1, anything else answered with an Error (0x42) message.
"""

from __future__ import annotations

import struct
from enum import IntEnum
from typing import Sequence

from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.wire import check_finite, check_unit_quaternions, to_zup_wxyz

PREAMBLE = 0xFA
#: Bus ID of the master device (every message of a single MTi).
BUS_ID = 0xFF
#: ``LEN`` value announcing an extended (u16) length.
EXTENDED_LENGTH = 0xFF
#: Longest data of a standard-length frame; longer data uses the extended length.
MAX_STANDARD_LENGTH = 254
MAX_EXTENDED_LENGTH = 0xFFFF
#: One MTData2 record header: data ID (u16), payload size (u8).
RECORD_HEADER = struct.Struct("!HB")
#: One SetOutputConfiguration entry: data ID (u16), output rate in Hz (u16; 0xFFFF: every sample).
OUTPUT_CONFIG_ENTRY = struct.Struct("!HH")
#: SampleTimeFine ticks per second.
SAMPLE_TIME_FINE_HZ = 10_000


class MID(IntEnum):
    """Message IDs used here; an acknowledgement is MID + 1."""

    REQ_DID = 0x00
    DEVICE_ID = 0x01
    GO_TO_MEASUREMENT = 0x10
    GO_TO_MEASUREMENT_ACK = 0x11
    GO_TO_CONFIG = 0x30
    GO_TO_CONFIG_ACK = 0x31
    MT_DATA2 = 0x36
    WAKE_UP = 0x3E
    WAKE_UP_ACK = 0x3F
    ERROR = 0x42
    SET_OUTPUT_CONFIGURATION = 0xC0
    SET_OUTPUT_CONFIGURATION_ACK = 0xC1


class XDI(IntEnum):
    """MTData2 data IDs written by :func:`encode_mtdata2` (float32 precision bits)."""

    PACKET_COUNTER = 0x1020
    SAMPLE_TIME_FINE = 0x1060
    QUATERNION = 0x2010
    ACCELERATION = 0x4020
    RATE_OF_TURN = 0x8020
    MAGNETIC_FIELD = 0xC020
    STATUS_WORD = 0xE020


#: Payload struct of each record.
RECORD_FORMATS = {
    XDI.PACKET_COUNTER: struct.Struct("!H"),
    XDI.SAMPLE_TIME_FINE: struct.Struct("!L"),
    XDI.QUATERNION: struct.Struct("!4f"),
    XDI.ACCELERATION: struct.Struct("!3f"),
    XDI.RATE_OF_TURN: struct.Struct("!3f"),
    XDI.MAGNETIC_FIELD: struct.Struct("!3f"),
    XDI.STATUS_WORD: struct.Struct("!L"),
}
#: Records of an MTData2 message unless configured otherwise, in this order.
DEFAULT_OUTPUTS = tuple(XDI)
#: Error codes of the Error message (one data byte).
ERROR_CODES = {0x03: "invalid period", 0x04: "invalid message", 0x1E: "timer overflow",
               0x20: "invalid baudrate", 0x21: "invalid parameter", 0x28: "device error"}
ERROR_INVALID_MESSAGE = 0x04
ERROR_INVALID_PARAMETER = 0x21


def checksum(body: bytes) -> int:
    """The checksum byte for ``body`` = every frame byte after the preamble, up to the checksum."""
    return -sum(body) & 0xFF


def encode_message(mid: int, data: bytes = b"", *, bus_id: int = BUS_ID) -> bytes:
    """One Xbus frame: preamble, bus ID, MID, length (extended beyond 254 bytes), data, checksum."""
    if not 0 <= mid <= 0xFF:
        raise ValueError(f"MID must be one byte, got {mid}")
    n = len(data)
    if n > MAX_EXTENDED_LENGTH:
        raise ValueError(f"Xbus data of {n} bytes exceeds {MAX_EXTENDED_LENGTH}")
    length = bytes([n]) if n <= MAX_STANDARD_LENGTH else bytes([EXTENDED_LENGTH]) + struct.pack("!H", n)
    body = bytes([bus_id, mid]) + length + bytes(data)
    return bytes([PREAMBLE]) + body + bytes([checksum(body)])


def sample_time_fine(device_time_ns: int) -> int:
    """SampleTimeFine ticks (10 kHz, rounded) of a device time in ns, modulo 2**32."""
    return ((int(device_time_ns) + 50_000) // 100_000) & 0xFFFFFFFF


def mtdata2_records(sample: ImuSample, outputs: Sequence[int] = DEFAULT_OUTPUTS) -> bytes:
    """The MTData2 data of ``sample``: one record per data ID in ``outputs``, in that order."""
    values = {}
    for xdi in outputs:
        xdi = XDI(xdi)
        if xdi in values:
            raise ValueError(f"data ID 0x{xdi:04X} requested twice")
        if xdi is XDI.PACKET_COUNTER:
            values[xdi] = (int(sample.counter) & 0xFFFF,)
        elif xdi is XDI.SAMPLE_TIME_FINE:
            values[xdi] = (sample_time_fine(sample.device_time_ns),)
        elif xdi is XDI.QUATERNION:
            check_unit_quaternions(sample.orientation, f"orientation of IMU {sample.device!r}")
            values[xdi] = tuple(to_zup_wxyz(sample.orientation))
        elif xdi is XDI.ACCELERATION:
            values[xdi] = tuple(check_finite(sample.acceleration, "acceleration"))
        elif xdi is XDI.RATE_OF_TURN:
            values[xdi] = tuple(check_finite(sample.rate_of_turn, "rate of turn"))
        elif xdi is XDI.MAGNETIC_FIELD:
            values[xdi] = tuple(check_finite(sample.magnetic_field, "magnetic field"))
        else:
            values[xdi] = (int(sample.status) & 0xFFFFFFFF,)
    out = bytearray()
    for xdi, v in values.items():
        fmt = RECORD_FORMATS[xdi]
        out += RECORD_HEADER.pack(xdi, fmt.size) + fmt.pack(*v)
    return bytes(out)


def encode_mtdata2(sample: ImuSample, outputs: Sequence[int] = DEFAULT_OUTPUTS) -> bytes:
    """One MTData2 (0x36) frame of ``sample`` with the records ``outputs`` (default: all of
    :class:`XDI`). Raises ``ValueError`` on non-finite values or a non-unit orientation."""
    return encode_message(MID.MT_DATA2, mtdata2_records(sample, outputs))


# ----------------------------------------------------------------------------------- device
class SimulatedMti:
    """The device side of the Xbus configuration dialogue of a single MTi.

    Feed it the bytes a host writes (:meth:`answer`, any chunking: partial frames wait for the
    rest, garbage before a preamble is skipped, frames with a bad checksum are dropped and counted);
    it returns the bytes the device would write back:

    * WakeUp (0x3E) -> WakeUpAck (0x3F), device in config state;
    * GoToConfig (0x30) -> 0x31, config state (no MTData2 output);
    * GoToMeasurement (0x10) -> 0x11, measurement state;
    * ReqDID (0x00) -> DeviceID (0x01, ``!L`` device ID), in either state;
    * SetOutputConfiguration (0xC0, N x ``'!HH'`` data ID + rate), config state only -> 0xC1
      echoing the configuration now in force; empty data asks for the current one. IDs other than
      :class:`XDI` are refused with Error 0x21 (invalid parameter), the configuration unchanged;
    * anything else, or a configuration message in measurement state -> Error (0x42) with code
      0x04 (invalid message).

    The device starts measuring with :data:`DEFAULT_OUTPUTS` (as an MTi does after power-on);
    :meth:`mtdata2` encodes a sample with the configured records, or returns None in config state.
    Rates are stored and echoed; the simulated device emits every configured record in each sample.
    """

    def __init__(self, device_id: int = 0x03601234, outputs: Sequence[int] = DEFAULT_OUTPUTS):
        self.device_id = int(device_id) & 0xFFFFFFFF
        self.measuring = True
        self.output_configuration: list[tuple[int, int]] = [(int(x), 0xFFFF) for x in outputs]
        self.frames_received = 0
        self.bad_checksums = 0
        self.bytes_skipped = 0
        self.errors_sent = 0
        self._buffer = bytearray()

    @property
    def outputs(self) -> tuple[int, ...]:
        """Data IDs of the current output configuration, in order."""
        return tuple(x for x, _ in self.output_configuration)

    def mtdata2(self, sample: ImuSample) -> bytes | None:
        """The MTData2 frame the device sends for ``sample`` now, or None in config state."""
        return encode_mtdata2(sample, self.outputs) if self.measuring else None

    def answer(self, incoming: bytes) -> bytes:
        """Take bytes from the host; return the bytes the device writes in reply (maybe none)."""
        self._buffer += incoming
        out = bytearray()
        buf = self._buffer
        while True:
            start = buf.find(bytes([PREAMBLE, BUS_ID]))
            if start < 0:
                keep = 1 if buf.endswith(bytes([PREAMBLE])) else 0
                self.bytes_skipped += len(buf) - keep
                del buf[: len(buf) - keep]
                break
            self.bytes_skipped += start
            del buf[:start]
            if len(buf) < 4:
                break
            n, head = buf[3], 4
            if n == EXTENDED_LENGTH:
                if len(buf) < 6:
                    break
                n, head = struct.unpack_from("!H", buf, 4)[0], 6
            if len(buf) < head + n + 1:
                break
            frame = bytes(buf[: head + n + 1])
            if sum(frame[1:]) & 0xFF:
                self.bad_checksums += 1
                self.bytes_skipped += 1
                del buf[:1]  # resynchronise after the bad preamble
                continue
            del buf[: head + n + 1]
            self.frames_received += 1
            out += self._reply(frame[2], frame[head: head + n])
        return bytes(out)

    def _error(self, code: int) -> bytes:
        self.errors_sent += 1
        return encode_message(MID.ERROR, bytes([code]))

    def _reply(self, mid: int, data: bytes) -> bytes:
        if mid == MID.WAKE_UP:
            self.measuring = False
            return encode_message(MID.WAKE_UP_ACK)
        if mid == MID.GO_TO_CONFIG:
            self.measuring = False
            return encode_message(MID.GO_TO_CONFIG_ACK)
        if mid == MID.GO_TO_MEASUREMENT:
            self.measuring = True
            return encode_message(MID.GO_TO_MEASUREMENT_ACK)
        if mid == MID.REQ_DID:
            return encode_message(MID.DEVICE_ID, struct.pack("!L", self.device_id))
        if mid == MID.SET_OUTPUT_CONFIGURATION and not self.measuring:
            if len(data) % OUTPUT_CONFIG_ENTRY.size:
                return self._error(ERROR_INVALID_PARAMETER)
            entries = [OUTPUT_CONFIG_ENTRY.unpack_from(data, i) for i in range(0, len(data), OUTPUT_CONFIG_ENTRY.size)]
            known = {int(x) for x in XDI}
            ids = [x for x, _ in entries]
            if any(x not in known for x in ids) or len(set(ids)) != len(ids):
                return self._error(ERROR_INVALID_PARAMETER)
            if entries:
                self.output_configuration = entries
            echo = b"".join(OUTPUT_CONFIG_ENTRY.pack(x, r) for x, r in self.output_configuration)
            return encode_message(MID.SET_OUTPUT_CONFIGURATION_ACK, echo)
        return self._error(ERROR_INVALID_MESSAGE)

"""Xsens MTi "Xbus" serial protocol: frames, MTData2 records, a stream parser and record decoder,
and a simulated device's replies.

Frame (as ``ethz-asl/ethzasl_xsens_driver``, ``nodes/mtdevice.py`` and ``nodes/mtdef.py``, reads it)::

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

Decoding: :class:`XbusParser` cuts a byte stream (any chunking) into frames, resynchronising
after garbage and bad checksums; :func:`decode_mtdata2` splits MTData2 data into records
(:data:`MTDATA2_RECORDS`, float32 and float64 precision); :func:`from_zup_wxyz` undoes the
encoder's frame change.

:class:`SimulatedMti` is the device's side of the configuration dialogue (WakeUp, GoToConfig,
SetOutputConfiguration, GoToMeasurement, ReqDID); every accepted message is acknowledged with
MID + 1, anything else answered with an Error (0x42) message.
"""

from __future__ import annotations

import math
import struct
from collections import Counter
from enum import IntEnum
from typing import MutableMapping, Sequence

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


# ----------------------------------------------------------------------------------- decoding
_SYNC = bytes([PREAMBLE, BUS_ID])


class XbusParser:
    """Cuts an Xbus byte stream, in any chunking, into frames ``(mid, data)``.

    Scans for ``FA FF``; reads the standard or extended length; checks the checksum. A partial
    frame at the end waits for more bytes (:meth:`push` them). Lengths are never trusted: an
    extended length of 254 or less (not a form the format allows) or one above ``max_length``
    (default 65535, the format's maximum; a decoder may set less) is refused like a bad checksum,
    and nothing is allocated for a claimed length — the parser only buffers bytes that arrived.

    :attr:`frames`: valid frames so far (a plain int: it changes with every frame). ``counters``
    (a :class:`collections.Counter`, shared with a decoder if given) counts the rest:
    ``bytes_skipped`` (bytes discarded while looking for a frame, including the preamble byte of
    each refused frame), ``resyncs`` (times sync was lost: a run of skipped bytes after a valid
    frame or at the start), ``bad_checksum``, ``bad_length``, ``cut_frames`` (partial frames given
    up by :meth:`flush`). After a refused frame the scan goes on one byte after its preamble, so a
    frame hidden behind a cut one is still found.
    """

    def __init__(self, max_length: int = MAX_EXTENDED_LENGTH, counters: MutableMapping[str, int] | None = None):
        if not 0 <= max_length <= MAX_EXTENDED_LENGTH:
            raise ValueError(f"max_length must be within 0..{MAX_EXTENDED_LENGTH}, got {max_length}")
        self.max_length = int(max_length)
        self.counters = counters if counters is not None else Counter()
        self.frames = 0
        self._buf = bytearray()
        self._pos = 0
        self._synced = True

    @property
    def pending(self) -> int:
        """Bytes held that are not yet part of a complete frame."""
        return len(self._buf) - self._pos

    def push(self, data: bytes) -> None:
        """Append bytes that arrived; :meth:`pop` the frames they complete."""
        if self._pos:
            del self._buf[: self._pos]
            self._pos = 0
        self._buf += data

    def feed(self, data: bytes) -> list[tuple[int, bytes]]:
        """:meth:`push` ``data`` and return every frame now complete, in order."""
        self.push(data)
        return self._scan(-1)

    def pop(self) -> tuple[int, bytes] | None:
        """The next complete frame ``(mid, data)`` from what was pushed, or None."""
        frames = self._scan(1)
        return frames[0] if frames else None

    def flush(self) -> list[tuple[int, bytes]]:
        """No more bytes are coming (end of stream, or a device gone quiet): give up on a partial
        frame (counted ``cut_frames``) and return the frames found behind its preamble."""
        out = []
        while True:
            out += self._scan(-1)
            if not self.pending:
                return out
            if self.pending > 1:  # a frame's start whose rest never came
                self.counters["cut_frames"] += 1
            self._skip(1)
            self._pos += 1

    def rest(self) -> bytes:
        """Remove and return the bytes not yet parsed (e.g. to hand them to another parser)."""
        out = bytes(self._buf[self._pos:])
        self._buf.clear()
        self._pos = 0
        return out

    def _skip(self, n: int) -> None:
        self.counters["bytes_skipped"] += n
        if self._synced:
            self.counters["resyncs"] += 1
            self._synced = False

    def _scan(self, limit: int) -> list[tuple[int, bytes]]:
        """Up to ``limit`` (-1: all) complete frames from the buffer, consuming them."""
        buf, pos, n = self._buf, self._pos, len(self._buf)
        out: list[tuple[int, bytes]] = []
        find = buf.find
        while len(out) != limit:
            i = find(_SYNC, pos)
            if i < 0:
                keep = n - 1 if n > pos and buf[n - 1] == PREAMBLE else n
                if keep > pos:
                    self._skip(keep - pos)
                pos = keep
                break
            if i > pos:
                self._skip(i - pos)
                pos = i
            if n - pos < 4:
                break
            length = buf[pos + 3]
            if length != EXTENDED_LENGTH:
                head = 4
                bad = length > self.max_length
            else:
                if n - pos < 6:
                    break
                length, head = (buf[pos + 4] << 8) | buf[pos + 5], 6
                bad = length <= MAX_STANDARD_LENGTH or length > self.max_length
            if bad:
                self.counters["bad_length"] += 1
                self._skip(1)
                pos += 1
                continue
            end = pos + head + length + 1
            if end > n:
                break  # a partial frame: wait for the rest
            data = bytes(buf[pos + head: end - 1])
            if (sum(data) + sum(buf[pos + 1: pos + head]) + buf[end - 1]) & 0xFF:
                self.counters["bad_checksum"] += 1
                self._skip(1)
                pos += 1  # resynchronise one byte after the bad preamble
                continue
            out.append((buf[pos + 2], data))
            pos = end
            self._synced = True
        self._pos = pos
        self.frames += len(out)
        return out


#: Base data ID (precision bits clear) -> (name, payload format). Float formats (``f``) are read
#: as float64 (``d``) when the ID's precision bits are 3. Coordinate-system bits (0x000C) other
#: than 0 (ENU) are not decoded: such IDs count as unknown.
MTDATA2_RECORDS: dict[int, tuple[str, str]] = {
    0x1010: ("utc", "!LHBBBBBB"),  # ns, year, month, day, hour, minute, second, flags
    0x1020: ("packet_counter", "!H"),
    0x1060: ("sample_time_fine", "!L"),
    0x1070: ("sample_time_coarse", "!L"),
    0x2010: ("quaternion", "!4f"),  # w, x, y, z: sensor to Z-up earth
    0x2020: ("rotation_matrix", "!9f"),
    0x2030: ("euler", "!3f"),  # roll, pitch, yaw, degrees
    0x4010: ("delta_v", "!3f"),
    0x4020: ("acceleration", "!3f"),
    0x4030: ("free_acceleration", "!3f"),
    0x8020: ("rate_of_turn", "!3f"),
    0x8030: ("delta_q", "!4f"),
    0xC020: ("magnetic_field", "!3f"),
    0xE010: ("status_byte", "!B"),
    0xE020: ("status_word", "!L"),
}
PRECISION_MASK = 0x0003
PRECISION_FLOAT32, PRECISION_FLOAT64 = 0x0, 0x3


def _record_table() -> dict[int, tuple[int, struct.Struct]]:
    table = {}
    for did, (_, fmt) in MTDATA2_RECORDS.items():
        table[did] = (did, struct.Struct(fmt))
        if "f" in fmt:
            table[did | PRECISION_FLOAT64] = (did, struct.Struct(fmt.replace("f", "d")))
    return table


_RECORDS = _record_table()
_FLOAT_IDS = frozenset(did for did, (_, fmt) in MTDATA2_RECORDS.items() if "f" in fmt)


def decode_mtdata2(data: bytes, counters: MutableMapping[str, int] | None = None) -> dict[int, tuple]:
    """The records of MTData2 ``data``: base data ID (:data:`MTDATA2_RECORDS`, precision bits
    clear) -> tuple of values (floats as Python floats, whatever the precision on the wire).

    Never raises on bad data; counts in ``counters``: ``unknown_id`` (skipped by its size),
    ``unsupported_precision`` (fixed-point 12.20 / 16.32 floats, skipped), ``bad_record_size``
    (a size that does not match its ID's format; skipped), ``truncated`` (a record header or
    payload running past the end: decoding stops there). A repeated ID keeps the last record.
    """
    if counters is None:
        counters = Counter()
    out: dict[int, tuple] = {}
    off, n = 0, len(data)
    unpack_header = RECORD_HEADER.unpack_from
    records = _RECORDS
    while off < n:
        if off + 3 > n:
            counters["truncated"] += 1
            break
        did, size = unpack_header(data, off)
        off += 3
        if off + size > n:
            counters["truncated"] += 1
            break
        entry = records.get(did)
        if entry is None:
            precision_only = (did & ~PRECISION_MASK) in _FLOAT_IDS
            counters["unsupported_precision" if precision_only else "unknown_id"] += 1
        elif entry[1].size != size:
            counters["bad_record_size"] += 1
        else:
            out[entry[0]] = entry[1].unpack_from(data, off)
        off += size
    return out


_H = math.sqrt(0.5)


def from_zup_wxyz(w: float, x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """Inverse of :func:`~dualhuman_builder.capture.wire.to_zup_wxyz` for one quaternion: an
    orientation in the MTi's Z-up earth frame (w, x, y, z) -> the same in our Y-up world as
    (x, y, z, w): ``ZUP_TO_YUP`` (-90 degrees about X) times ``q``. Plain floats (fast)."""
    return _H * (x - w), _H * (y + z), _H * (z - y), _H * (w + x)


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
        self.errors_sent = 0
        self._parser = XbusParser()

    @property
    def frames_received(self) -> int:
        """Valid frames received from the host."""
        return self._parser.frames

    @property
    def bad_checksums(self) -> int:
        """Frames from the host dropped for a bad checksum."""
        return self._parser.counters["bad_checksum"]

    @property
    def bytes_skipped(self) -> int:
        """Bytes from the host discarded while resynchronising (garbage, bad frames' preambles)."""
        return self._parser.counters["bytes_skipped"]

    @property
    def outputs(self) -> tuple[int, ...]:
        """Data IDs of the current output configuration, in order."""
        return tuple(x for x, _ in self.output_configuration)

    def mtdata2(self, sample: ImuSample) -> bytes | None:
        """The MTData2 frame the device sends for ``sample`` now, or None in config state."""
        return encode_mtdata2(sample, self.outputs) if self.measuring else None

    def answer(self, incoming: bytes) -> bytes:
        """Take bytes from the host; return the bytes the device writes in reply (maybe none)."""
        return b"".join(self._reply(mid, data) for mid, data in self._parser.feed(incoming))

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

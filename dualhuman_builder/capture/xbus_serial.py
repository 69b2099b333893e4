"""``xbus://`` — an Xsens MTi on a serial port (USB adapter, pty) or pyserial's ``loop://``.

URL: ``xbus:///dev/ttyUSB0?baud=921600`` (an absolute device or pty path: three slashes),
``xbus://COM3`` (a port name), ``xbus://loop`` (pyserial's ``loop://``). Parameters:

``baud``     line rate (default 115200, the MTi's factory setting);
``config``   ``1`` runs the configuration dialogue when the source opens (default), ``0`` takes
             the device as it is (configured elsewhere; the default for ``loop``, which only
             echoes): GoToConfig -> ack 0x31, SetOutputConfiguration with every record of
             :data:`~.wire.xbus.DEFAULT_OUTPUTS` -> ack 0xC1 whose echo must name the same records,
             GoToMeasurement -> ack 0x11. MTData2 frames still streaming before the device acks
             GoToConfig are skipped (counted ``dialogue_skipped_frames``). No reply within
             ``timeout``, or an Error (0x42) reply, raises :class:`SourceError` naming the step
             and the device's error code;
``timeout``  seconds to wait for each acknowledgement (default 2);
``rate``     output rate in Hz asked for the sensor records (default 65535 = 0xFFFF: every
             sample, the device's full rate); counters and time always go with every sample;
``device``   the device name of the samples (default: the port's basename, e.g. ``ttyUSB0``,
             or ``loop``).

:class:`XbusSource` returns what each serial read delivered as a :class:`RawPacket` (bytes left
over from the dialogue come first); a serial error while reading (device unplugged, pty closed)
raises :class:`SourceLost`. :class:`XbusDecoder` turns the byte stream into :class:`ImuSample` s.
Transport counters: ``reads``, ``read_bytes`` (packets and bytes handed out),
``dialogue_skipped_frames`` (frames other than the awaited ack during the dialogue).

:class:`SequenceTracker` and :class:`Unwrapper` (wrapping packet counters and device clocks) are
shared with :mod:`.mti_can`.
"""

from __future__ import annotations

import math
import operator
import os
import struct
import time
from collections import Counter
from typing import MutableMapping

import numpy as np

from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.sources import (Decoder, RawPacket, Source, SourceError, SourceLost, now_ns,
                                               number_param, parse_source_url)  # fmt: skip
from dualhuman_builder.capture.wire.xbus import (DEFAULT_OUTPUTS, ERROR_CODES, MID, MTDATA2_RECORDS,
                                                 OUTPUT_CONFIG_ENTRY, PRECISION_MASK, RECORD_HEADER,
                                                 SAMPLE_TIME_FINE_HZ, XbusParser, decode_mtdata2, encode_message,
                                                 from_zup_wxyz)  # fmt: skip

DEFAULT_BAUD = 115_200
DEFAULT_TIMEOUT_S = 2.0
#: Output rate meaning "with every sample" in SetOutputConfiguration.
EVERY_SAMPLE = 0xFFFF
#: Longest frame the decoder accepts: an MTi's MTData2 frame is a few hundred bytes at most, so
#: a longer claimed length is garbage and is refused at once rather than waited for.
MAX_FRAME_DATA = 4096
#: Most bytes one :meth:`XbusSource.read` returns.
MAX_READ = 1 << 16
#: A device is ``live`` while its last sample is younger than this (ns).
LIVE_NS = 500_000_000
TICK_NS = 1_000_000_000 // SAMPLE_TIME_FINE_HZ
#: A quaternion whose norm is further than this from 1 (or that is not finite) is refused
#: (``bad_quaternion``; shared with :mod:`.mti_can`, whose int16 rounding moves the norm by < 1e-4).
QUATERNION_NORM_TOLERANCE = 0.01
_NORM2_LO, _NORM2_HI = (1.0 - QUATERNION_NORM_TOLERANCE) ** 2, (1.0 + QUATERNION_NORM_TOLERANCE) ** 2

_NAN_Q = (float("nan"),) * 4
_NAN_V = (float("nan"),) * 3
#: Records an :class:`ImuSample` is made of (base data IDs): PacketCounter, SampleTimeFine,
#: SampleTimeCoarse, Quaternion, Acceleration, RateOfTurn, MagneticField, StatusWord, StatusByte.
_FIELD_IDS = (0x1020, 0x1060, 0x1070, 0x2010, 0x4020, 0x8020, 0xC020, 0xE020, 0xE010)
#: Record layouts (one per data length) an :class:`XbusDecoder` compiles at most.
MAX_LAYOUTS = 16
_MT_DATA2, _ERROR = int(MID.MT_DATA2), int(MID.ERROR)
_H = math.sqrt(0.5)  # from_zup_wxyz, inlined on the fast path


# ----------------------------------------------------------------------------------- counters
class Unwrapper:
    """Unwraps a ``bits``-bit counter (a device clock) into a monotonic integer: each value is
    placed at the signed difference (within half the range) from the previous one. The first
    value is taken as it is (0 .. 2**bits - 1)."""

    __slots__ = ("mask", "half", "last", "value")

    def __init__(self, bits: int):
        self.mask = (1 << bits) - 1
        self.half = 1 << (bits - 1)
        self.last: int | None = None
        self.value = 0

    def __call__(self, raw: int) -> int:
        if self.last is None:
            self.value = raw
        else:
            d = (raw - self.last) & self.mask
            self.value += d - (self.mask + 1) if d >= self.half else d
        self.last = raw
        return self.value

    def rebase(self, value: int) -> None:
        """Continue unwrapping from the unwrapped ``value`` (as if it had just been seen)."""
        self.last, self.value = value & self.mask, value


class SequenceTracker:
    """Loss accounting of a wrapping packet counter (u16 by default), unwrapped internally.

    :meth:`update` counts, in ``counters``: ``lost`` (counter values skipped; decreased again
    when a skipped value arrives late), ``duplicate`` (a value already seen among the last
    ``window``; the caller drops the sample) and ``out_of_order`` (a value older than the newest,
    not seen before; kept). Returns False for a duplicate."""

    def __init__(self, bits: int = 16, window: int = 1024):
        if window & (window - 1) or window < 1:
            raise ValueError(f"window must be a power of two, got {window}")
        self.unwrap = Unwrapper(bits)
        self.newest: int | None = None
        self.first: int | None = None
        self._ring = [-1] * window  # the last values seen, by value modulo window
        self._mask = window - 1

    def update(self, raw: int, counters: MutableMapping[str, int]) -> bool:
        u = self.unwrap(raw)
        newest = self.newest
        if newest is None:
            self.newest = self.first = u
        elif u > newest:
            if u > newest + 1:
                counters["lost"] += u - newest - 1
            self.newest = u
        else:
            self.unwrap.rebase(newest)  # keep unwrapping from the newest value, not the late one
            if newest - u <= self._mask and self._ring[u & self._mask] == u:
                counters["duplicate"] += 1
                return False
            counters["out_of_order"] += 1
            if newest - u <= self._mask and u > self.first and counters["lost"] > 0:
                counters["lost"] -= 1
        self._ring[u & self._mask] = u
        return True


# ----------------------------------------------------------------------------------- decoder
class _Layout:
    """One MTData2 record layout compiled into a single struct: ``unpack`` reads every header
    and value at once; the frame has this layout when ``headers(values) == expected`` (each
    record's data ID and size). ``fields``: ``(start, stop)`` in the values of each of
    :data:`_FIELD_IDS` (-1, -1: absent). Only layouts whose records are all known and sized
    right are compiled, so the result equals :func:`decode_mtdata2`'s."""

    __slots__ = ("unpack", "headers", "expected", "fields", "pick", "status_at")

    @classmethod
    def compile(cls, data: bytes) -> _Layout:
        fmt, positions, expected, where = ["!"], [], [], {}
        off, index = 0, 0
        while off < len(data):
            did, size = RECORD_HEADER.unpack_from(data, off)
            fmt.append("HB")
            positions += [index, index + 1]
            expected += [did, size]
            base = did & ~PRECISION_MASK
            rec_fmt = MTDATA2_RECORDS[base][1].lstrip("!")
            if did & PRECISION_MASK:
                rec_fmt = rec_fmt.replace("f", "d")
            fmt.append(rec_fmt)
            n_values = len(struct.unpack("!" + rec_fmt, bytes(size)))
            where[base] = (index + 2, index + 2 + n_values)
            index += 2 + n_values
            off += 3 + size
        self = cls()
        self.unpack = struct.Struct("".join(fmt)).unpack
        self.headers = operator.itemgetter(*positions)
        self.expected = tuple(expected)
        self.fields = tuple(where.get(did, (-1, -1)) for did in _FIELD_IDS)
        # every record of a complete sample present: one C call picks its 15 numbers
        needed = (0x1020, 0x1060, 0x2010, 0x4020, 0x8020, 0xC020)
        self.pick = None
        if all(did in where for did in needed):
            self.pick = operator.itemgetter(*(i for did in needed for i in range(*where[did])))
        status = where.get(0xE020, where.get(0xE010))
        self.status_at = -1 if status is None else status[0]
        return self


class XbusDecoder(Decoder):
    """Xbus byte stream -> one :class:`ImuSample` per MTData2 frame.

    Sample fields (``device``: the name given): ``counter`` the PacketCounter (u16 as sent; -1 if
    the record is absent); ``device_time_ns`` SampleTimeFine (10 kHz ticks, 100 us) unwrapped
    across its u32 wrap (every 4.97 days) so it never jumps back, as ns — or SampleTimeCoarse
    (s) if only that is sent, else -1; ``host_time_ns`` the host time of the packet that
    completed the frame; ``orientation`` the Quaternion record turned from the MTi's Z-up earth
    frame to our Y-up world, (x, y, z, w); ``acceleration``, ``rate_of_turn``,
    ``magnetic_field`` as sent (sensor frame); ``status`` the StatusWord (else StatusByte, else 0).
    A record missing from a frame leaves NaN in its field and counts the sample ``incomplete``. A
    value that cannot be a measurement is not passed on either: a Quaternion with a NaN or
    infinite value or a norm off 1 by more than :data:`QUATERNION_NORM_TOLERANCE` leaves NaN in
    ``orientation`` (``bad_quaternion``), an Acceleration, RateOfTurn or MagneticField record with
    a NaN or infinite value leaves NaN in its field (``bad_vector``); the sample keeps its counter
    and times.

    Counters: ``packets``, ``bytes``, ``samples``; the parser's ``frames``, ``bytes_skipped``,
    ``resyncs``, ``bad_checksum``, ``bad_length``, ``cut_frames`` (:class:`~.wire.xbus.XbusParser`;
    lengths above :data:`MAX_FRAME_DATA` refused; :meth:`finish` gives up a partial last frame);
    the records' ``unknown_id``, ``unsupported_precision``, ``bad_record_size``, ``truncated``
    (:func:`~.wire.xbus.decode_mtdata2`); ``empty_frame`` (an MTData2 frame with no records:
    no sample); ``incomplete``; ``bad_quaternion``, ``bad_vector``;
    ``lost``, ``duplicate`` (dropped), ``out_of_order`` (kept) from the PacketCounter
    (:class:`SequenceTracker`); other frames by MID as ``mid_0x31`` etc. An Error (0x42) frame
    also becomes a ``device-error`` event.
    """

    def __init__(self, device: str = "mti", max_frame_data: int = MAX_FRAME_DATA):
        self._packets = self._bytes = self._samples = 0
        super().__init__()
        self.device = device
        self.parser = XbusParser(max_length=max_frame_data, counters=self._counters)
        self.sequence = SequenceTracker(16)
        self.time_ticks = Unwrapper(32)
        self.last_host_ns: int | None = None
        self._last_packet_ns = 0
        self._layouts: dict[int, _Layout] = {}

    @property
    def counters(self) -> Counter:
        """The counters (see the class docstring). The per-packet ones are kept as plain ints
        (a Counter increment costs about as much as decoding a record) and copied in here."""
        c = self._counters
        c["packets"], c["bytes"], c["samples"] = self._packets, self._bytes, self._samples
        c["frames"] = self.parser.frames
        return c

    @counters.setter
    def counters(self, value: Counter) -> None:
        self._counters = value

    def feed(self, packet: RawPacket) -> list:
        data = packet.data
        self._packets += 1
        self._bytes += len(data)
        self._last_packet_ns = packet.host_time_ns
        return self._decode(self.parser.feed(data), packet.host_time_ns)

    def finish(self) -> list:
        """The frames behind a cut frame left at the end of the stream (see XbusParser.flush)."""
        return self._decode(self.parser.flush(), self._last_packet_ns)

    def _decode(self, frames: list, host_ns: int) -> list:
        out = []
        for mid, payload in frames:
            if mid == _MT_DATA2:
                sample = self._sample(payload, host_ns)
                if sample is not None:
                    out.append(sample)
            else:
                self._counters[f"mid_0x{mid:02X}"] += 1
                if mid == _ERROR:
                    code = payload[0] if payload else None
                    what = "no code" if code is None else f"0x{code:02X} ({ERROR_CODES.get(code, 'unknown error')})"
                    self.event(host_ns, "device-error", self.device, f"the MTi sent Error {what}")
        if out:
            self._samples += len(out)
            self.last_host_ns = out[-1].host_time_ns
        return out

    def _sample(self, data: bytes, host_ns: int) -> ImuSample | None:
        layout = self._layouts.get(len(data))
        if layout is not None:  # fast path: the layout every frame of a configured device has
            values = layout.unpack(data)
            if layout.headers(values) == layout.expected:
                if layout.pick is None:
                    return self._build([None if a < 0 else values[a:b] for a, b in layout.fields], host_ns)
                pc, stf, w, x, y, z, *vectors = layout.pick(values)
                if not self.sequence.update(pc, self._counters):
                    return None
                if _NORM2_LO <= w * w + x * x + y * y + z * z <= _NORM2_HI and math.isfinite(sum(vectors)):
                    floats = np.array((_H * (x - w), _H * (y + z), _H * (z - y), _H * (w + x), *vectors))
                else:  # a bad value (NaN and inf fail both tests): checked record by record
                    floats = self._floats((w, x, y, z), vectors[0:3], vectors[3:6], vectors[6:9])
                return ImuSample(self.device, pc, self.time_ticks(stf) * TICK_NS, host_ns, floats[0:4], floats[4:7],
                                 floats[7:10], floats[10:13], 0 if layout.status_at < 0 else values[layout.status_at])
        if not data:
            self._counters["empty_frame"] += 1
            return None
        found: Counter = Counter()
        rec = decode_mtdata2(data, found)
        if found:
            self._counters.update(found)
        elif len(self._layouts) < MAX_LAYOUTS:
            self._layouts[len(data)] = _Layout.compile(data)
        return self._build([rec.get(did) for did in _FIELD_IDS], host_ns)

    def _build(self, rec: list, host_ns: int) -> ImuSample | None:
        counters = self._counters
        pc, stf, coarse, q, acc, gyr, mag, word, byte = rec
        complete = True
        if pc is not None:
            if not self.sequence.update(pc[0], counters):
                return None
            counter = pc[0]
        else:
            counter, complete = -1, False
        if stf is not None:
            device_ns = self.time_ticks(stf[0]) * TICK_NS
        else:
            complete = False
            device_ns = coarse[0] * 1_000_000_000 if coarse is not None else -1
        if not complete or q is None or acc is None or gyr is None or mag is None:
            counters["incomplete"] += 1
        floats = self._floats(q, acc, gyr, mag)
        return ImuSample(self.device, counter, device_ns, host_ns, floats[0:4], floats[4:7], floats[7:10],
                         floats[10:13], (word or byte or (0,))[0])  # fmt: skip

    def _floats(self, q, acc, gyr, mag) -> np.ndarray:
        """Orientation (Y-up x, y, z, w), acceleration, rate of turn, magnetic field as one (13,)
        array (four views of it: a quarter of the allocations); NaN for a record that is missing
        (None) or holds a bad value (counted ``bad_quaternion`` / ``bad_vector``)."""
        if q is not None:
            w, x, y, z = q
            if not _NORM2_LO <= w * w + x * x + y * y + z * z <= _NORM2_HI:  # NaN and inf fail too
                self._counters["bad_quaternion"] += 1
                q = None
        vectors = []
        for v in (acc, gyr, mag):
            if v is not None and not all(map(math.isfinite, v)):
                self._counters["bad_vector"] += 1
                v = None
            vectors += v or _NAN_V
        return np.array((*(from_zup_wxyz(*q) if q is not None else _NAN_Q), *vectors))

    def recover(self) -> None:
        """After an exception in decoding (see :class:`~.sources.Decoder`): drop the bytes of a
        partial frame and the compiled layouts (rebuilt from the next frames)."""
        self.parser.rest()
        self._layouts.clear()

    def status(self, now_ns: int) -> dict:
        """``{device: {"last_ns": host time of the last sample (None before the first), "live"}}``."""
        last = self.last_host_ns
        return {self.device: {"last_ns": last, "live": last is not None and now_ns - last < LIVE_NS}}


# ----------------------------------------------------------------------------------- source
def _parse_xbus_url(url: str, params: tuple[str, ...]) -> tuple[str, str, dict]:
    """(pyserial port or URL, default device name, query) of an ``xbus://`` URL."""
    parts, query = parse_source_url(url, params)
    netloc, path = parts.netloc, parts.path
    if netloc == "loop" and path in ("", "/"):
        return "loop://", "loop", query
    if netloc and path not in ("", "/"):
        raise SourceError(f"{url!r} names a host {netloc!r} and a path {path!r}",
                          fix=f"write xbus:///{netloc}{path} (three slashes: an absolute device path)")  # fmt: skip
    if netloc:
        return netloc, netloc, query
    if path not in ("", "/"):
        return path, os.path.basename(path.rstrip("/")), query
    raise SourceError(f"{url!r} names no serial port", fix="write xbus:///dev/ttyUSB0 or xbus://loop")


class XbusSource(Source):
    """An MTi on a serial port; see the module docstring for the URL. ``port``: an already-open
    pyserial-like object (``read``, ``write``, ``in_waiting``, ``timeout``; e.g. a shared
    ``serial.serial_for_url("loop://")``) used instead of opening the URL's port, and left open
    by :meth:`close`."""

    kind = "xbus"
    PARAMS = ("baud", "config", "timeout", "rate", "device")

    def __init__(self, url: str, port=None):
        import serial

        super().__init__(url)
        target, _, query = _parse_xbus_url(url, self.PARAMS)
        self.port_name = target
        self.baud = number_param(query, "baud", int, DEFAULT_BAUD)
        self.timeout_s = number_param(query, "timeout", float, DEFAULT_TIMEOUT_S)
        self.rate = number_param(query, "rate", int, EVERY_SAMPLE)
        config = query.get("config", "0" if target == "loop://" else "1")
        if config not in ("0", "1"):
            raise SourceError(f"config={config!r} in {url!r}", fix="write config=1 (configure the MTi) or config=0")
        if self.baud <= 0 or not self.timeout_s > 0 or not 1 <= self.rate <= 0xFFFF:
            raise SourceError(f"bad baud, timeout or rate in {url!r}",
                              fix="baud and timeout must be positive, rate within 1..65535 Hz")  # fmt: skip
        self.decoder = self.make_decoder(url)
        self._own_port = port is None
        if port is None:
            try:
                if target == "loop://":
                    port = serial.serial_for_url(target, baudrate=self.baud, timeout=0.1)
                else:
                    port = serial.Serial(target, baudrate=self.baud, timeout=0.1, exclusive=True)
            except (serial.SerialException, OSError, ValueError) as e:
                raise SourceError(f"cannot open serial port {target} for {url!r} ({e})", fix=_open_fix(e)) from None
        self.port = port
        self._timeout_set = getattr(port, "timeout", None)
        self._pending: list[RawPacket] = []
        if config == "1":
            try:
                self._configure()
            except BaseException:
                self._close_port()
                raise

    @classmethod
    def make_decoder(cls, url: str) -> XbusDecoder:
        _, default_name, query = _parse_xbus_url(url, cls.PARAMS)
        return XbusDecoder(query.get("device") or default_name)

    # ---- configuration dialogue
    def _configure(self) -> None:
        parser = XbusParser(max_length=MAX_FRAME_DATA)
        self._command(parser, "GoToConfig", MID.GO_TO_CONFIG, b"", MID.GO_TO_CONFIG_ACK)
        counters_and_time = {0x1020, 0x1060}
        entries = [(int(x), EVERY_SAMPLE if int(x) in counters_and_time else self.rate) for x in DEFAULT_OUTPUTS]
        request = b"".join(OUTPUT_CONFIG_ENTRY.pack(x, r) for x, r in entries)
        echo = self._command(parser, "SetOutputConfiguration", MID.SET_OUTPUT_CONFIGURATION, request,
                             MID.SET_OUTPUT_CONFIGURATION_ACK)  # fmt: skip
        size = OUTPUT_CONFIG_ENTRY.size
        echoed = [OUTPUT_CONFIG_ENTRY.unpack_from(echo, i) for i in range(0, len(echo) - len(echo) % size, size)]
        if len(echo) % size or [x for x, _ in echoed] != [x for x, _ in entries]:
            raise SourceError(f"SetOutputConfiguration on {self.port_name}: the MTi kept "
                              f"{[hex(x) for x, _ in echoed]} instead of {[hex(x) for x, _ in entries]}",
                              fix="check that the device is an MTi with these outputs, or configure it "
                                  "elsewhere and open with config=0")  # fmt: skip
        if echoed != entries:
            self.decoder.event(now_ns(), "config-rate", self.decoder.device,
                               f"the MTi set output rates {echoed} (asked {entries})")
        self._command(parser, "GoToMeasurement", MID.GO_TO_MEASUREMENT, b"", MID.GO_TO_MEASUREMENT_ACK)
        rest = parser.rest()
        if rest:  # the start of the first data frame(s) after the ack: the decoder's
            self._pending.append(RawPacket(now_ns(), rest))
        self.decoder.event(now_ns(), "configured", self.decoder.device,
                           f"{self.port_name}: measuring with records {[hex(x) for x, _ in entries]}")

    def _command(self, parser: XbusParser, step: str, mid: int, data: bytes, ack: int) -> bytes:
        """Send one message; the data of its acknowledgement. Frames before it are skipped."""
        import serial

        try:
            self.port.write(encode_message(mid, data))
            deadline = time.monotonic() + self.timeout_s
            flushed: list[tuple[int, bytes]] = []
            while True:
                frame = flushed.pop(0) if flushed else parser.pop()
                if frame is not None:
                    rmid, rdata = frame
                    if rmid == ack:
                        return rdata
                    if rmid == MID.ERROR:
                        code = rdata[0] if rdata else None
                        what = "no code" if code is None else f"0x{code:02X} ({ERROR_CODES.get(code, 'unknown error')})"
                        raise SourceError(f"{step} failed on {self.port_name}: the MTi answered Error {what}",
                                          fix="check the device model and firmware; or configure it elsewhere "
                                              "and open with config=0")  # fmt: skip
                    self.counters["dialogue_skipped_frames"] += 1
                    continue
                if time.monotonic() >= deadline:
                    raise SourceError(f"no reply to {step} from {self.port_name} within {self.timeout_s:g} s",
                                      fix=f"check that an MTi is powered and connected here and that baud={self.baud} "
                                          "is its line rate (factory default 115200); for a device configured "
                                          "elsewhere use config=0")  # fmt: skip
                data = self._read_bytes(0.05)
                if data:
                    parser.push(data)
                elif parser.pending:
                    # quiet for 50 ms with a frame's start pending: that frame was cut (bytes
                    # dropped on the line) and the ack may wait behind its preamble
                    flushed = parser.flush()
        except (serial.SerialException, OSError) as e:
            raise SourceError(f"{step} on {self.port_name}: serial error ({e})",
                              fix="check the cable and that no other program uses the port") from None  # fmt: skip

    # ---- reading
    def _read_bytes(self, timeout: float) -> bytes:
        port = self.port
        n = port.in_waiting
        if n:
            return port.read(min(n, MAX_READ))
        if self._timeout_set != timeout:
            port.timeout = timeout
            self._timeout_set = timeout
        first = port.read(1)
        if not first:
            return b""
        n = port.in_waiting
        return first + port.read(min(n, MAX_READ - 1)) if n else first

    def read(self, timeout: float) -> list[RawPacket]:
        """What one serial read delivered within ``timeout`` s, as one packet ([] if nothing);
        :class:`SourceLost` when the port fails (device unplugged, pty closed)."""
        import serial

        if self.closed:
            return []
        if self._pending:
            out, self._pending = self._pending, []
            self.counters["reads"] += len(out)
            self.counters["read_bytes"] += sum(len(p.data) for p in out)
            return out
        try:
            data = self._read_bytes(max(0.0, timeout))
        except (serial.SerialException, OSError) as e:
            raise SourceLost(f"serial port {self.port_name} failed while reading ({e}): the MTi was unplugged "
                             "or the port closed",
                             fix="reconnect the device and start the take again") from None  # fmt: skip
        if not data:
            return []
        self.counters["reads"] += 1
        self.counters["read_bytes"] += len(data)
        return [RawPacket(now_ns(), data)]

    def _close_port(self) -> None:
        if self._own_port:
            try:
                self.port.close()
            except Exception:  # closing a port that already failed
                pass

    def close(self) -> None:
        if not self.closed:
            self._close_port()
        super().close()


def _open_fix(e: BaseException) -> str:
    import errno

    code = getattr(e, "errno", None)
    text = str(e)
    if code == errno.EACCES or "Permission denied" in text:
        return "add your user to the dialout group (sudo usermod -aG dialout $USER) and log in again"
    if code == errno.ENOENT or "No such file" in text:
        return "is the MTi plugged in? list serial ports with `python -m serial.tools.list_ports`"
    if "lock" in text:
        return "another program (or a second recorder) holds this port; close it first"
    return "check the port name, that the device is connected, and that no other program uses it"

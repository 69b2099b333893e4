"""``mti+can://INTERFACE/CHANNEL`` — an Xsens MTi-600 on a CAN bus, through python-can.

URL: ``mti+can://socketcan/can0``, ``mti+can://virtual/studio`` (python-can's in-process bus),
``mti+can://pcan/PCAN_USBBUS1``; the channel is the path after the first slash (so
``mti+can://slcan//dev/ttyACM0`` names ``/dev/ttyACM0``). Opened with
``can.Bus(interface=INTERFACE, channel=CHANNEL[, bitrate=...])``. Parameters:

``bitrate``  bits/s handed to python-can (interfaces that set it themselves, like socketcan,
             ignore it: there ``ip link`` sets it);
``device``   the device name of the samples (default: the channel, e.g. ``can0``).

:meth:`MtiCanSource.read` returns each received frame as a :class:`RawPacket` holding the 16-byte
SocketCAN ``struct can_frame`` (:func:`~.wire.mti_can.pack_can_frame`); error frames pass
through (the decoder counts them). A bus that fails while reading (interface down, adapter
unplugged, bus shut down) raises :class:`SourceLost` — after the frames already received in that
read have been returned. :meth:`~MtiCanSource.close` ends the source cleanly: later reads return
nothing. Transport counters: ``frames``, ``fd_frames`` (CAN FD frames: not an MTi's, dropped).
"""

from __future__ import annotations

import math
from collections import Counter

import numpy as np

from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.sources import (Decoder, RawPacket, Source, SourceError, SourceLost, now_ns,
                                               number_param, parse_source_url)  # fmt: skip
from dualhuman_builder.capture.wire.mti_can import (CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_FRAME, CAN_RTR_FLAG, DLC, CanId,
                                                    decode_can_signals, pack_can_frame, unpack_can_frame)  # fmt: skip
from dualhuman_builder.capture.xbus_serial import LIVE_NS, QUATERNION_NORM_TOLERANCE, SequenceTracker, Unwrapper

#: Most frames one :meth:`MtiCanSource.read` returns.
MAX_BATCH = 4096
#: Most distinct CAN error classes remembered (each new one is a ``bus-error`` event); further
#: classes are only counted, so hostile error frames cannot grow the decoder.
MAX_ERROR_CLASSES = 64

_SAMPLE_TIME, _GROUP_COUNTER, _STATUS_WORD, _QUATERNION = (int(CanId.SAMPLE_TIME), int(CanId.GROUP_COUNTER),
                                                          int(CanId.STATUS_WORD), int(CanId.QUATERNION))
_RATE_OF_TURN, _ACCELERATION = int(CanId.RATE_OF_TURN), int(CanId.ACCELERATION)
_MAGNETIC_FIELD = int(CanId.MAGNETIC_FIELD)
_FREE_ACCELERATION, _EULER, _TEMPERATURE = int(CanId.FREE_ACCELERATION), int(CanId.EULER), int(CanId.TEMPERATURE)
_FLAGS = CAN_EFF_FLAG | CAN_RTR_FLAG | CAN_ERR_FLAG
_DLC = {int(k): v for k, v in DLC.items()}
#: Frames whose values fill an :class:`ImuSample`; a group without one of them is ``incomplete``.
REQUIRED = frozenset(int(i) for i in (CanId.GROUP_COUNTER, CanId.STATUS_WORD, CanId.QUATERNION, CanId.RATE_OF_TURN,
                                      CanId.ACCELERATION, CanId.MAGNETIC_FIELD))  # fmt: skip
_EXTRA_IDS = frozenset(int(i) for i in (CanId.FREE_ACCELERATION, CanId.EULER, CanId.TEMPERATURE))
_H = math.sqrt(0.5)
_NAN = float("nan")


class MtiCanDecoder(Decoder):
    """MTi-600 CAN frames (SocketCAN ``can_frame`` packets) -> one :class:`ImuSample` per sample.

    Grouping: a SampleTime frame (0x05) starts a sample; the frames that follow belong to it until
    the next SampleTime, which emits it (:meth:`finish` emits the last). A frame before any
    SampleTime is an ``orphan_frames``. A frame whose ID the group already holds is a
    ``duplicate_frame`` when its data is the same (also a repeated SampleTime of the same value)
    and is ignored; with other data it means the next sample's SampleTime was lost: the group is
    emitted and the frames up to the next SampleTime are ``orphan_frames`` (that sample is lost:
    it has no time). Limit: after a lost SampleTime, the next sample's frames whose IDs the
    group lacks (its own were lost) still join it — two losses in a row cannot be told apart.

    Sample fields: ``counter`` the GroupCounter (u16 as sent, -1 if missing); ``device_time_ns``
    SampleTime (u32 microseconds, unwrapped across its wrap every 71.6 minutes, so it never
    jumps back) as ns; ``host_time_ns`` the host time of the group's last frame; ``orientation``
    the int16 quaternion (2**-15), normalised and turned from the MTi's Z-up earth frame to our
    Y-up world (x, y, z, w); ``rate_of_turn`` rad/s (2**-9), ``acceleration`` m/s^2 (2**-8),
    ``magnetic_field`` a.u. (2**-10), sensor frame; ``status`` the StatusWord (0 if missing). A
    missing frame leaves NaN (or -1 / 0) in its field and counts the sample ``incomplete``.

    FreeAcceleration (0x35), Euler (0x22) and Temperature (0x51) have no :class:`ImuSample` field:
    they are decoded, counted (``free_acceleration``, ``euler``, ``temperature``) and the latest
    values kept in :attr:`extras` (``free_acceleration`` (3,) m/s^2 in our Y-up world, ``euler``
    (roll, pitch, yaw) radians in the MTi's Z-up earth frame, ``temperature`` degrees Celsius,
    each with the ``device_time_ns`` of its sample).

    Counters: ``packets``, ``bytes``, ``frames`` (MTi frames accepted), ``samples``;
    ``bad_frame`` (not a 16-byte can_frame, or a length field over 8, whatever its flags),
    ``unknown_id`` (IDs not in the table, extended IDs), ``bad_length`` (wrong DLC for the ID;
    ignored), ``remote_frames``, ``error_frames`` (also a ``bus-error`` event for each of the first
    :data:`MAX_ERROR_CLASSES` error classes), ``orphan_frames``, ``duplicate_frame``,
    ``empty_group`` (a SampleTime with nothing after it; dropped), ``incomplete``,
    ``bad_quaternion`` (norm off by more than :data:`QUATERNION_NORM_TOLERANCE`; NaN); ``lost``,
    ``duplicate`` (a repeated GroupCounter; the sample is dropped), ``out_of_order`` from the
    GroupCounter (:class:`~.xbus_serial.SequenceTracker`; a sample whose GroupCounter frame alone
    was lost also shows as ``lost``).
    """

    def __init__(self, device: str = "mti-can"):
        self._packets = self._bytes = self._frames = self._samples = 0
        super().__init__()
        self.device = device
        self.sequence = SequenceTracker(16)
        self.time_us = Unwrapper(32)
        self.extras: dict[str, tuple] = {}
        self.last_host_ns: int | None = None
        self._group: dict[int, bytes] | None = None
        self._group_time = -1
        self._group_host = 0
        self._error_classes: set[int] = set()

    @property
    def counters(self) -> Counter:
        """The counters (see the class docstring); the per-frame ones are plain ints copied in."""
        c = self._counters
        c["packets"], c["bytes"], c["frames"], c["samples"] = self._packets, self._bytes, self._frames, self._samples
        return c

    @counters.setter
    def counters(self, value: Counter) -> None:
        self._counters = value

    def feed(self, packet: RawPacket) -> list:
        data = packet.data
        self._packets += 1
        self._bytes += len(data)
        if len(data) != 16:
            self._counters["bad_frame"] += 1
            return []
        can_id, dlc, payload = CAN_FRAME.unpack(data)
        if dlc > 8:  # not a classic CAN frame, whatever its flags say
            self._counters["bad_frame"] += 1
            return []
        if can_id & _FLAGS:
            self._flagged(data, packet.host_time_ns)
            return []
        expected = _DLC.get(can_id)
        if expected is None:
            self._counters["unknown_id"] += 1
            return []
        if dlc != expected:
            self._counters["bad_length"] += 1
            return []
        self._frames += 1
        body = payload[:dlc]
        group = self._group
        if can_id == _SAMPLE_TIME:
            if group is not None and body == group[_SAMPLE_TIME]:
                self._counters["duplicate_frame"] += 1
                return []
            out = self._emit()
            self._group = {_SAMPLE_TIME: body}
            self._group_host = packet.host_time_ns
            return out
        if group is None:
            self._counters["orphan_frames"] += 1
            return []
        held = group.get(can_id)
        if held is None:
            group[can_id] = body
            self._group_host = packet.host_time_ns
            return []
        if held == body:
            self._counters["duplicate_frame"] += 1
            return []
        out = self._emit()  # the next sample's SampleTime was lost
        self._group = None
        self._counters["orphan_frames"] += 1
        return out

    def finish(self) -> list:
        out = self._emit()
        self._group = None
        return out

    def recover(self) -> None:
        """After an exception in decoding (see :class:`~.sources.Decoder`): drop the group being
        assembled."""
        self._group = None

    def _flagged(self, data: bytes, host_ns: int) -> None:
        frame = unpack_can_frame(data)
        if frame.is_error_frame:
            self._counters["error_frames"] += 1
            cls = frame.arbitration_id
            if cls not in self._error_classes and len(self._error_classes) < MAX_ERROR_CLASSES:
                self._error_classes.add(cls)
                self.event(host_ns, "bus-error", self.device,
                           f"CAN error frame, error class 0x{cls:X} (linux/can/error.h); more are counted")  # fmt: skip
        elif frame.is_remote_frame:
            self._counters["remote_frames"] += 1
        else:  # extended identifiers: not the MTi's
            self._counters["unknown_id"] += 1

    def _emit(self) -> list:
        group = self._group
        if group is None:
            return []
        self._group = None
        counters = self._counters
        if len(group) == 1:
            counters["empty_group"] += 1
            return []
        counter = -1
        if _GROUP_COUNTER in group:
            (counter,) = decode_can_signals(_GROUP_COUNTER, group[_GROUP_COUNTER])
            if not self.sequence.update(counter, counters):
                return []
        (us,) = decode_can_signals(_SAMPLE_TIME, group[_SAMPLE_TIME])
        device_ns = self.time_us(us) * 1000
        if not REQUIRED.issubset(group):
            counters["incomplete"] += 1
        q = (_NAN,) * 4
        if _QUATERNION in group:
            w, x, y, z = decode_can_signals(_QUATERNION, group[_QUATERNION])
            norm = math.sqrt(w * w + x * x + y * y + z * z)
            if abs(norm - 1.0) <= QUATERNION_NORM_TOLERANCE:
                s = _H / norm  # Z-up (w, x, y, z) -> Y-up (x, y, z, w), as wire.xbus.from_zup_wxyz
                q = (s * (x - w), s * (y + z), s * (z - y), s * (w + x))
            else:
                counters["bad_quaternion"] += 1
        vectors = []
        for cid in (_ACCELERATION, _RATE_OF_TURN, _MAGNETIC_FIELD):
            body = group.get(cid)
            vectors += decode_can_signals(cid, body) if body is not None else (_NAN,) * 3
        status = decode_can_signals(_STATUS_WORD, group[_STATUS_WORD])[0] if _STATUS_WORD in group else 0
        if not _EXTRA_IDS.isdisjoint(group):
            self._keep_extras(group, device_ns)
        floats = np.array((*q, *vectors))
        self._samples += 1
        self.last_host_ns = self._group_host
        return [ImuSample(self.device, counter, device_ns, self._group_host, floats[0:4], floats[4:7], floats[7:10],
                          floats[10:13], status)]  # fmt: skip

    def _keep_extras(self, group: dict[int, bytes], device_ns: int) -> None:
        counters = self._counters
        if _FREE_ACCELERATION in group:
            x, y, z = decode_can_signals(_FREE_ACCELERATION, group[_FREE_ACCELERATION])
            self.extras["free_acceleration"] = ((x, z, -y), device_ns)  # Z-up earth -> Y-up world
            counters["free_acceleration"] += 1
        if _EULER in group:
            self.extras["euler"] = (decode_can_signals(_EULER, group[_EULER]), device_ns)
            counters["euler"] += 1
        if _TEMPERATURE in group:
            self.extras["temperature"] = (decode_can_signals(_TEMPERATURE, group[_TEMPERATURE]), device_ns)
            counters["temperature"] += 1

    def status(self, now_ns: int) -> dict:
        """``{device: {"last_ns": host time of the last sample (None before the first), "live"}}``."""
        last = self.last_host_ns
        return {self.device: {"last_ns": last, "live": last is not None and now_ns - last < LIVE_NS}}


def _parse_can_url(url: str, params: tuple[str, ...]) -> tuple[str, str, dict]:
    parts, query = parse_source_url(url, params)
    interface, channel = parts.netloc, parts.path[1:] if parts.path.startswith("/") else parts.path
    if not interface or not channel:
        raise SourceError(f"{url!r} does not name a CAN interface and channel",
                          fix="write mti+can://INTERFACE/CHANNEL, e.g. mti+can://socketcan/can0 or "
                              "mti+can://virtual/studio")  # fmt: skip
    return interface, channel, query


class MtiCanSource(Source):
    """An MTi-600 on a CAN bus; see the module docstring for the URL. ``bus``: an open python-can
    bus to read instead of opening one (left open by :meth:`close`)."""

    kind = "mti-can"
    PARAMS = ("device", "bitrate")

    def __init__(self, url: str, bus=None):
        import can

        super().__init__(url)
        self.interface, self.channel, query = _parse_can_url(url, self.PARAMS)
        bitrate = number_param(query, "bitrate", int, None)
        if bitrate is not None and bitrate <= 0:
            raise SourceError(f"bitrate={bitrate} in {url!r}", fix="give the bus bit rate in bits/s, e.g. 1000000")
        self.decoder = self.make_decoder(url)
        self._own_bus = bus is None
        if bus is None:
            kwargs = {} if bitrate is None else {"bitrate": bitrate}
            try:
                bus = can.Bus(interface=self.interface, channel=self.channel, **kwargs)
            except Exception as e:  # python-can raises CanError, OSError, ValueError, ImportError by backend
                fix = _open_fix(self.interface, self.channel, bitrate, e)
                raise SourceError(f"cannot open CAN {self.interface}/{self.channel} for {url!r} "
                                  f"({type(e).__name__}: {e})", fix=fix) from None  # fmt: skip
        self.bus = bus
        self._failure: BaseException | None = None

    @classmethod
    def make_decoder(cls, url: str) -> MtiCanDecoder:
        _, channel, query = _parse_can_url(url, cls.PARAMS)
        return MtiCanDecoder(query.get("device") or channel.rstrip("/").rsplit("/", 1)[-1])

    def read(self, timeout: float) -> list[RawPacket]:
        """The frames received within ``timeout`` s (up to :data:`MAX_BATCH`), each as a
        16-byte can_frame packet; :class:`SourceLost` when the bus fails."""
        import can

        if self.closed:
            return []
        if self._failure is not None:
            self._lost(self._failure)
        out: list[RawPacket] = []
        try:
            msg = self.bus.recv(max(0.0, timeout))
            while msg is not None:
                t = now_ns()
                try:
                    out.append(RawPacket(t, pack_can_frame(msg)))
                except ValueError:
                    self.counters["fd_frames"] += 1
                if len(out) >= MAX_BATCH:
                    break
                msg = self.bus.recv(0.0)
        except (can.CanError, OSError) as e:
            if not out:
                self._lost(e)
            self._failure = e  # hand over what arrived; raise on the next read
        self.counters["frames"] += len(out)
        return out

    def _lost(self, e: BaseException):
        raise SourceLost(f"CAN bus {self.interface}/{self.channel} failed while reading ({type(e).__name__}: {e}): "
                         "the interface went down, the adapter was unplugged or the bus was shut down",
                         fix=f"check the adapter and `ip -details link show {self.channel}` (socketcan); "
                             "then start the take again") from None  # fmt: skip

    def close(self) -> None:
        if not self.closed and self._own_bus:
            try:
                self.bus.shutdown()
            except Exception:  # a bus that already failed
                pass
        super().close()


def _open_fix(interface: str, channel: str, bitrate: int | None, e: BaseException) -> str:
    import can

    if isinstance(e, can.CanInterfaceNotImplementedError) or isinstance(e, ImportError):
        return ("name an interface python-can has and whose driver is installed, e.g. socketcan, pcan, kvaser, "
                f"slcan, virtual (python-can knows: {', '.join(sorted(can.VALID_INTERFACES))})")  # fmt: skip
    if interface == "socketcan":
        return (f"bring the interface up: sudo ip link set {channel} up type can bitrate {bitrate or 1000000} "
                f"(a test bus: sudo ip link add dev {channel} type vcan && sudo ip link set {channel} up)")  # fmt: skip
    return f"check that the {interface} adapter is connected, its driver installed, and the channel name right"

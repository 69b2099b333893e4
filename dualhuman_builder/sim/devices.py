"""Simulated devices on real transports: players that put encoded packets onto a UDP socket, a
serial port or a CAN bus at the recorded timing, with seeded fault injection whose every effect is
recorded.

A :class:`Packet` is what a device sends in one write: MVN or tracker datagram bytes, an Xbus
frame (or the :class:`ImuSample` a :class:`~dualhuman_builder.capture.wire.xbus.SimulatedMti`
encodes when it is sent, so that its output configuration applies), or a ``can.Message``. Each
carries a schedule time in int64 ns and a stream name (``mvn/0``, ``vive/<serial>``, ...). The
``*_packets`` helpers build them from typed samples, timed by the samples' device clock (or, with
``clock="host"``, by their host receive time: use that when merging streams whose device clocks
are offset from each other, as simulated trackers are).

A player merges every stream it is given in time order (stable), then sends packet *k* at
``start + (time_k - time_0) / speed`` of ``time.perf_counter`` (``speed`` N plays N times faster,
``math.inf`` as fast as it can), sleeping in between; a packet that is late is sent at once.
:meth:`Player.play` runs in the calling thread, :meth:`Player.start` / :meth:`Player.stop` /
:meth:`Player.join` in a background thread. The :class:`PlayReport` says what was sent.

Faults (:class:`Faults`) act between encoder and transport, in this order: outages (a stream
silent during given intervals), random loss, byte corruption, reordering (a packet held back
behind up to ``max_displacement`` later ones), duplication (a copy right after the original).
Each kind draws from its own random stream seeded by ``(seed, kind)``, so the same seed gives the
same faults and changing one rate does not move the others. :class:`FaultLog` records exactly
which packets (indices into :attr:`Player.packets`) were lost, silenced, duplicated, reordered
and corrupted (with the byte offsets flipped).
"""

from __future__ import annotations

import abc
import errno
import fcntl
import math
import os
import select
import socket
import struct
import termios
import threading
import time
import tty
from collections import Counter
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from typing import Iterable, Literal, Sequence, Union

import can
import numpy as np

from dualhuman_builder.capture.samples import ImuSample, SuitFrame, TrackerSample
from dualhuman_builder.capture.wire.mti_can import encode_can
from dualhuman_builder.capture.wire.mvn import DEFAULT_MAX_DATAGRAM, encode_frame
from dualhuman_builder.capture.wire.vive_udp import encode_tracker
from dualhuman_builder.capture.wire.xbus import SimulatedMti

Payload = Union[bytes, can.Message, ImuSample]
Clock = Literal["device", "host"]


@dataclass(frozen=True)
class Packet:
    """One write of a device: ``data`` scheduled at ``time_ns`` (int64 ns), of ``stream``."""

    time_ns: int
    data: Payload
    stream: str = ""


def _time(sample, clock: Clock) -> int:
    if clock not in ("device", "host"):
        raise ValueError(f"clock must be 'device' or 'host', got {clock!r}")
    return int(sample.device_time_ns if clock == "device" else sample.host_time_ns)


def mvn_packets(
    frames: Iterable[SuitFrame],
    *,
    clock: Clock = "device",
    time_code: bool = True,
    prologue: Sequence[bytes] = (),
    max_datagram: int = DEFAULT_MAX_DATAGRAM,
    stream: str | None = None,
) -> list[Packet]:
    """MVN datagrams of ``frames``: per frame its type-02 pieces and (``time_code``) type 25, all
    at the frame's time; ``prologue`` datagrams (e.g. meta and scale) go first, at the first
    frame's time. Stream name: ``stream`` or ``mvn/<character>``."""
    out: list[Packet] = []
    for frame in frames:
        name = stream or f"mvn/{frame.character}"
        t = _time(frame, clock)
        if not out:
            out += [Packet(t, bytes(d), name) for d in prologue]
        out += [Packet(t, d, name) for d in encode_frame(frame, time_code=time_code, max_datagram=max_datagram)]
    return out


def tracker_packets(
    samples: Iterable[TrackerSample], *, clock: Clock = "device", stream: str | None = None
) -> list[Packet]:
    """One bridge datagram per tracker sample; stream ``stream`` or ``vive/<serial>``."""
    return [Packet(_time(s, clock), encode_tracker(s), stream or f"vive/{s.serial}") for s in samples]


def xbus_packets(samples: Iterable[ImuSample], *, clock: Clock = "device", stream: str | None = None) -> list[Packet]:
    """IMU samples for a :class:`SerialPlayer`, encoded as MTData2 frames when sent (with the
    simulated MTi's output configuration at that moment); stream ``stream`` or ``xbus/<device>``."""
    return [Packet(_time(s, clock), s, stream or f"xbus/{s.device}") for s in samples]


def can_packets(samples: Iterable[ImuSample], *, clock: Clock = "device", stream: str | None = None) -> list[Packet]:
    """The MTi-600 CAN frames of each sample (SampleTime first); stream ``stream`` or ``can/<device>``."""
    return [Packet(_time(s, clock), m, stream or f"can/{s.device}") for s in samples for m in encode_can(s)]


def merge(*streams: Iterable[Packet]) -> list[Packet]:
    """Packets of all ``streams`` in time order; ties keep the order given (stable)."""
    return sorted((p for s in streams for p in s), key=lambda p: p.time_ns)


# ----------------------------------------------------------------------------------- faults
@dataclass(frozen=True)
class Outage:
    """A device silent from ``start_s`` to ``stop_s`` (seconds after the first packet of the
    play, stop excluded); ``stream``: an fnmatch pattern of stream names, None for all."""

    start_s: float
    stop_s: float
    stream: str | None = None


@dataclass(frozen=True)
class Faults:
    """Seeded faults between encoder and transport. Probabilities are per packet:

    ``loss`` (dropped), ``corrupt`` (``corrupt_bytes`` random bytes XOR-ed with a non-zero mask),
    ``reorder`` (held back behind 1..``max_displacement`` later packets, uniformly), ``duplicate``
    (sent twice in a row); ``outages`` silence streams for intervals.
    """

    seed: int = 0
    loss: float = 0.0
    reorder: float = 0.0
    max_displacement: int = 3
    duplicate: float = 0.0
    corrupt: float = 0.0
    corrupt_bytes: int = 1
    outages: tuple[Outage, ...] = ()

    def __post_init__(self):
        for name in ("loss", "reorder", "duplicate", "corrupt"):
            p = getattr(self, name)
            if not 0.0 <= p <= 1.0:
                raise ValueError(f"Faults.{name} must be a probability in [0, 1], got {p}")
        if self.max_displacement < 1 or self.corrupt_bytes < 1:
            raise ValueError("Faults.max_displacement and Faults.corrupt_bytes must be at least 1")
        for o in self.outages:
            if not o.stop_s > o.start_s:
                raise ValueError(f"outage must end after it starts: {o}")


_LOSS, _CORRUPT, _REORDER, _DISPLACE, _DUPLICATE, _CORRUPT_BYTES = range(1, 7)


@dataclass
class FaultPlan:
    """What :func:`plan_faults` decided. ``order``: packet indices in sending order (a duplicate
    appears twice in a row); ``send_time_ns``: each emission's schedule time (a held-back packet
    goes right after the packet it now follows); ``reordered``: index -> number of later packets
    sent before it (as it really came out); ``corrupt``: indices whose bytes get flipped."""

    order: list[int]
    send_time_ns: list[int]
    lost: list[int]
    outage: list[int]
    duplicated: list[int]
    reordered: dict[int, int]
    corrupt: frozenset[int]


def plan_faults(packets: Sequence[Packet], faults: Faults | None) -> FaultPlan:
    """Decide every fault for ``packets`` (in play order). Same seed, same packets: same plan."""
    n = len(packets)
    times = np.array([p.time_ns for p in packets], dtype=np.int64)
    if faults is None or n == 0:
        idx = list(range(n))
        return FaultPlan(idx, times.tolist(), [], [], [], {}, frozenset())

    def rng(kind: int) -> np.random.Generator:
        return np.random.default_rng([faults.seed, kind])

    rel_s = (times - times[0]) / 1e9
    silent = np.zeros(n, bool)
    for o in faults.outages:
        hit = (rel_s >= o.start_s) & (rel_s < o.stop_s)
        if o.stream is not None:
            hit &= np.array([fnmatchcase(p.stream, o.stream) for p in packets], bool)
        silent |= hit
    lost = (rng(_LOSS).random(n) < faults.loss) & ~silent
    alive = ~silent & ~lost
    corrupt = (rng(_CORRUPT).random(n) < faults.corrupt) & alive
    held = rng(_REORDER).random(n) < faults.reorder
    shift = rng(_DISPLACE).integers(1, faults.max_displacement + 1, n)
    dup = (rng(_DUPLICATE).random(n) < faults.duplicate) & alive

    survivors = np.flatnonzero(alive)
    pos = np.arange(len(survivors), dtype=np.float64)
    key = pos + np.where(held[survivors], shift[survivors] + 0.5, 0.0)
    order = survivors[np.argsort(key, kind="stable")]
    overtaken = np.zeros(len(order), np.int64)  # later packets sent before each one
    for lag in range(1, 2 * faults.max_displacement + 3):  # wide enough: keys move <= max_displacement
        overtaken[lag:] += order[:-lag] > order[lag:]
    send = np.maximum.accumulate(times[order]) if len(order) else times[order]
    emit, emit_t = [], []
    for i, t in zip(order.tolist(), send.tolist()):
        emit += [i, i] if dup[i] else [i]
        emit_t += [t, t] if dup[i] else [t]
    return FaultPlan(
        order=emit, send_time_ns=emit_t, lost=np.flatnonzero(lost).tolist(), outage=np.flatnonzero(silent).tolist(),
        duplicated=np.flatnonzero(dup).tolist(),
        reordered={int(i): int(k) for i, k in zip(order, overtaken) if k > 0},
        corrupt=frozenset(np.flatnonzero(corrupt).tolist()),
    )


def corrupt_payload(data: bytes | can.Message, *, seed: int, index: int, n_bytes: int):
    """``data`` with ``n_bytes`` distinct bytes (of a CAN frame: of its data field) XOR-ed with a
    random non-zero mask, drawn from ``(seed, index)``; returns ``(new data, sorted offsets)``."""
    raw = bytes(data.data) if isinstance(data, can.Message) else bytes(data)
    if not raw:
        return data, ()
    g = np.random.default_rng([seed, _CORRUPT_BYTES, index])
    offsets = np.sort(g.choice(len(raw), size=min(n_bytes, len(raw)), replace=False))
    masks = g.integers(1, 256, size=len(offsets))
    out = bytearray(raw)
    for o, m in zip(offsets.tolist(), masks.tolist()):
        out[o] ^= m
    if isinstance(data, can.Message):
        new = can.Message(arbitration_id=data.arbitration_id, data=bytes(out), is_extended_id=data.is_extended_id,
                          timestamp=data.timestamp, is_remote_frame=data.is_remote_frame)
        return new, tuple(offsets.tolist())
    return bytes(out), tuple(offsets.tolist())


@dataclass
class FaultLog:
    """What a play did. Indices refer to :attr:`Player.packets`. ``sent``: indices as written to
    the transport, in order (a duplicate twice); ``lost``, ``outage``, ``duplicated``: per the
    plan; ``reordered``: index -> later packets sent before it; ``corrupted``: index -> byte
    offsets flipped (in the datagram, frame, or CAN data field)."""

    sent: list[int] = field(default_factory=list)
    lost: list[int] = field(default_factory=list)
    outage: list[int] = field(default_factory=list)
    duplicated: list[int] = field(default_factory=list)
    reordered: dict[int, int] = field(default_factory=dict)
    corrupted: dict[int, tuple[int, ...]] = field(default_factory=dict)

    def counts(self) -> dict[str, int]:
        """Number of packets affected by each kind of fault, and of writes."""
        return {"sent": len(self.sent), "lost": len(self.lost), "outage": len(self.outage),
                "duplicated": len(self.duplicated), "reordered": len(self.reordered),
                "corrupted": len(self.corrupted)}


@dataclass
class PlayReport:
    """Outcome of a play: ``packets`` given, ``sent`` writes (duplicates included) and their
    ``bytes_sent``, writes ``per_stream``, ``faults``; ``suppressed``: packets the device did not
    send (a simulated MTi in config state); ``replies``: answers to host messages written (serial);
    ``send_errors``: writes the transport refused (UDP); ``elapsed_s``; ``completed`` False when
    stopped early."""

    packets: int = 0
    sent: int = 0
    bytes_sent: int = 0
    per_stream: Counter = field(default_factory=Counter)
    faults: FaultLog = field(default_factory=FaultLog)
    suppressed: list[int] = field(default_factory=list)
    replies: int = 0
    send_errors: int = 0
    elapsed_s: float = 0.0
    completed: bool = False


# ----------------------------------------------------------------------------------- players
class Player(abc.ABC):
    """Base of the players: merging, pacing, faults, threading. Subclasses transmit."""

    def __init__(self, *, speed: float = 1.0, faults: Faults | None = None):
        if not speed > 0:
            raise ValueError(f"speed must be > 0 (math.inf: as fast as possible), got {speed}")
        self.speed = float(speed)
        self.faults = faults
        self._given: list[Packet] = []
        self._merged: list[Packet] | None = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._error: BaseException | None = None
        self.report: PlayReport | None = None
        #: ``(perf_counter seconds, schedule ns)``: the wall instant at which schedule time
        #: ``origin_ns`` is due. None: the play's own start and its first packet. Players that
        #: stand for devices of one studio share one (see :meth:`share_clock`), so a thread that
        #: starts late sends its overdue packets at once instead of shifting its whole stream.
        self.epoch: tuple[float, int] | None = None

    def add(self, packets: Iterable[Packet]) -> Player:
        """Add a stream (or several, already merged); merged with the others in time order."""
        self._given.extend(packets)
        self._merged = None
        return self

    @property
    def packets(self) -> list[Packet]:
        """Every packet given, in play order (time, then order given); the indices of the logs."""
        if self._merged is None:
            self._merged = merge(self._given)
        return self._merged

    # ---- running
    def play(self) -> PlayReport:
        """Send everything at the scheduled times, in this thread; returns the report."""
        packets = self.packets
        plan = plan_faults(packets, self.faults)
        log = FaultLog(lost=plan.lost, outage=plan.outage, duplicated=plan.duplicated, reordered=plan.reordered)
        report = self.report = PlayReport(packets=len(packets), faults=log)
        seed = self.faults.seed if self.faults else 0
        if self.epoch is not None:
            start, t0 = self.epoch
        else:
            start, t0 = time.perf_counter(), (packets[0].time_ns if packets else 0)
        last_i, last_data = -1, None
        completed = True
        for i, t_ns in zip(plan.order, plan.send_time_ns):
            if math.isfinite(self.speed):
                self._wait_until(start + (t_ns - t0) / 1e9 / self.speed)
            if self._stop.is_set():
                completed = False
                break
            self._service()
            if i == last_i:  # the duplicate, right after its original
                data = last_data
            else:
                data = self._encode(packets[i])
                if data is None:
                    report.suppressed.append(i)
                elif i in plan.corrupt:
                    data, offsets = corrupt_payload(data, seed=seed, index=i, n_bytes=self.faults.corrupt_bytes)
                    if offsets:
                        log.corrupted[i] = offsets
                last_i, last_data = i, data
            if data is None:
                continue
            written = self._transmit(data)
            if written is None:
                report.send_errors += 1
                continue
            report.sent += 1
            report.bytes_sent += written
            report.per_stream[packets[i].stream] += 1
            log.sent.append(i)
        if completed:
            self._finish()
        report.completed = completed and not self._stop.is_set()
        report.elapsed_s = time.perf_counter() - start
        return report

    @staticmethod
    def share_clock(players: Iterable[Player], lead_s: float = 0.05) -> None:
        """Give ``players`` one schedule clock: schedule time 0 of the earliest packet among them
        falls ``lead_s`` seconds from now on every player. Devices of one studio run on one
        physical time; without this, each player's thread start (which varies by tens of ms on a
        loaded machine) would offset its whole stream against the others'. Call before
        :meth:`start`; packets must be timed on one clock (``clock="host"``)."""
        players = list(players)
        firsts = [p.packets[0].time_ns for p in players if p.packets]
        if not firsts:
            return
        epoch = (time.perf_counter() + lead_s, min(firsts))
        for p in players:
            p.epoch = epoch

    def start(self) -> Player:
        """Play in a background thread."""
        if self._thread is not None:
            raise RuntimeError("this player was already started")

        def run():
            try:
                self.play()
            except BaseException as e:  # handed to join()
                self._error = e

        self._thread = threading.Thread(target=run, name=f"{type(self).__name__}", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        """Ask a running play to stop before its next packet."""
        self._stop.set()

    def join(self, timeout: float | None = None) -> PlayReport | None:
        """Wait for the background play; re-raises its exception; returns the report."""
        if self._thread is not None:
            self._thread.join(timeout)
        if self._error is not None:
            raise self._error
        return self.report

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def close(self) -> None:
        """Release what the player opened itself (nothing by default)."""

    def __enter__(self) -> Player:
        return self

    def __exit__(self, *exc) -> None:
        self.stop()
        try:
            self.join()
        finally:
            self.close()

    # ---- subclass hooks
    def _encode(self, packet: Packet):
        if isinstance(packet.data, ImuSample):
            raise TypeError(f"{type(self).__name__} sends bytes or CAN frames, not IMU samples "
                            f"(stream {packet.stream!r})")
        return packet.data

    @abc.abstractmethod
    def _transmit(self, data) -> int | None:
        """Write one encoded packet to the transport; the bytes written, or None if refused."""

    def _service(self) -> None:
        """Called before each packet (a serial device answers its host here)."""

    def _wait_until(self, deadline: float) -> None:
        while not self._stop.is_set():
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                return
            self._stop.wait(remaining)

    def _finish(self) -> None:
        """Called after the last packet of a play that was not stopped."""


class UdpPlayer(Player):
    """Sends each packet as one UDP datagram to ``address`` ``(host, port)``; several streams
    (two suits on one MVN port, trackers) merged in time order onto one socket. ``sock``: a socket
    to send from (default: a new one, closed by :meth:`close`). A datagram the kernel refuses
    (no route, receiver gone) is counted in ``send_errors``, as a device that keeps sending."""

    def __init__(self, address: tuple[str, int], *, speed: float = 1.0, faults: Faults | None = None,
                 sock: socket.socket | None = None):
        super().__init__(speed=speed, faults=faults)
        self.address = (address[0], int(address[1]))
        self._own = sock is None
        if sock is None:
            family = socket.getaddrinfo(self.address[0], self.address[1], type=socket.SOCK_DGRAM)[0][0]
            sock = socket.socket(family, socket.SOCK_DGRAM)
        self.sock = sock

    def _encode(self, packet: Packet):
        data = super()._encode(packet)
        if not isinstance(data, (bytes, bytearray)):
            raise TypeError(f"UdpPlayer sends bytes, got {type(data).__name__} in stream {packet.stream!r}")
        return data

    def _transmit(self, data: bytes) -> int | None:
        try:
            return self.sock.sendto(data, self.address)
        except OSError:
            return None

    def close(self) -> None:
        if self._own:
            self.sock.close()


class SerialPlayer(Player):
    """Writes Xbus frames to a serial port and answers the host through a :class:`SimulatedMti`.

    ``port``: a pyserial port (``serial.serial_for_url("loop://")``, ``serial.Serial`` on a pty's
    slave path) or a :class:`PtyMaster`; anything with ``write``, ``read`` and ``in_waiting``.
    :class:`ImuSample` packets are encoded when sent, with the MTi's current output configuration;
    in config state they are not sent (``suppressed``). Bytes packets are written as they are.
    Between packets (every ``poll_s`` at most) the player reads what the host wrote, feeds it to
    ``mti`` and writes its answers; ``linger_s`` keeps answering that long after the last packet.
    ``respond=False`` never reads: use it on ``loop://``, which echoes the device's own bytes.
    """

    def __init__(self, port, *, speed: float = 1.0, faults: Faults | None = None, mti: SimulatedMti | None = None,
                 respond: bool = True, linger_s: float = 0.0, poll_s: float = 0.002):
        super().__init__(speed=speed, faults=faults)
        self.port = port
        self.mti = mti if mti is not None else SimulatedMti()
        self.respond = respond
        self.linger_s = float(linger_s)
        self.poll_s = float(poll_s)

    def add_samples(
        self, samples: Iterable[ImuSample], *, clock: Clock = "device", stream: str | None = None
    ) -> SerialPlayer:
        """Add IMU samples as an MTData2 stream (see :func:`xbus_packets`)."""
        self.add(xbus_packets(samples, clock=clock, stream=stream))
        return self

    def _encode(self, packet: Packet):
        if isinstance(packet.data, ImuSample):
            return self.mti.mtdata2(packet.data)
        if isinstance(packet.data, can.Message):
            raise TypeError(f"SerialPlayer sends bytes, got a CAN frame in stream {packet.stream!r}")
        return packet.data

    def _transmit(self, data: bytes) -> int:
        self.port.write(data)
        return len(data)

    def _service(self) -> None:
        if not self.respond:
            return
        waiting = self.port.in_waiting
        if not waiting:
            return
        before = self.mti.frames_received
        reply = self.mti.answer(self.port.read(waiting))
        if reply:
            self.port.write(reply)
        if self.report is not None:
            self.report.replies += self.mti.frames_received - before

    def _wait_until(self, deadline: float) -> None:
        while not self._stop.is_set():
            self._service()
            remaining = deadline - time.perf_counter()
            if remaining <= 0:
                return
            self._stop.wait(min(remaining, self.poll_s) if self.respond else remaining)

    def _finish(self) -> None:
        if self.respond and self.linger_s > 0:
            self._wait_until(time.perf_counter() + self.linger_s)


class CanPlayer(Player):
    """Sends ``can.Message`` packets on a python-can bus (e.g.
    ``can.Bus(interface="virtual", channel=...)``); the bus stays the caller's to shut down."""

    def __init__(self, bus: can.BusABC, *, speed: float = 1.0, faults: Faults | None = None, send_timeout: float = 1.0):
        super().__init__(speed=speed, faults=faults)
        self.bus = bus
        self.send_timeout = send_timeout

    def add_samples(
        self, samples: Iterable[ImuSample], *, clock: Clock = "device", stream: str | None = None
    ) -> CanPlayer:
        """Add IMU samples as MTi-600 CAN frames (see :func:`can_packets`)."""
        self.add(can_packets(samples, clock=clock, stream=stream))
        return self

    def _encode(self, packet: Packet):
        data = super()._encode(packet)
        if not isinstance(data, can.Message):
            raise TypeError(f"CanPlayer sends can.Message, got {type(data).__name__} in stream {packet.stream!r}")
        return data

    def _transmit(self, msg: can.Message) -> int:
        self.bus.send(msg, timeout=self.send_timeout)
        return len(msg.data)


# ----------------------------------------------------------------------------------- pty
class PtyMaster:
    """A pseudo-terminal whose master end a simulated device holds, as its serial port; a host
    opens :attr:`slave_path` (e.g. ``serial.Serial(pty.slave_path)``) as if it were a USB adapter.

    The line discipline is put in raw mode at once (no echo, no CR/LF translation, no XON/XOFF
    bytes eaten), and the slave stays open for the pty's lifetime so the master never sees a
    hang-up. ``read`` never blocks; ``write`` waits at most ``write_timeout`` seconds for a host
    that does not read (then ``TimeoutError``) — or, with ``drop_when_full``, drops at once what
    the full pty buffer does not take, as a device streaming to a host that is not listening
    does, counting it in :attr:`dropped_bytes` (a host that starts reading later sees a cut frame
    first and must resynchronise).
    """

    def __init__(self, write_timeout: float = 5.0, drop_when_full: bool = False):
        self.fd, self._slave_fd = os.openpty()
        tty.setraw(self._slave_fd)
        self.slave_path = os.ttyname(self._slave_fd)
        os.set_blocking(self.fd, False)
        self.write_timeout = write_timeout
        self.drop_when_full = drop_when_full
        self.dropped_bytes = 0

    @property
    def in_waiting(self) -> int:
        """Bytes the host wrote that are waiting to be read."""
        return struct.unpack("i", fcntl.ioctl(self.fd, termios.FIONREAD, b"\0\0\0\0"))[0]

    def read(self, size: int = 1) -> bytes:
        try:
            return os.read(self.fd, size)
        except BlockingIOError:
            return b""
        except OSError as e:  # EIO: no slave open (cannot happen while we hold it)
            if e.errno == errno.EIO:
                return b""
            raise

    def write(self, data: bytes) -> int:
        view = memoryview(bytes(data))
        deadline = time.monotonic() + self.write_timeout
        while view:
            try:
                n = os.write(self.fd, view)
                view = view[n:]
            except BlockingIOError:
                if self.drop_when_full:
                    self.dropped_bytes += len(view)
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"host did not read {self.slave_path} for {self.write_timeout} s") from None
                select.select([], [self.fd], [], min(remaining, 0.1))
        return len(data)

    def flush(self) -> None:
        """Writes are handed to the pty at once; nothing to flush."""

    def close(self) -> None:
        for fd in (self.fd, self._slave_fd):
            try:
                os.close(fd)
            except OSError:
                pass

    def __enter__(self) -> PtyMaster:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

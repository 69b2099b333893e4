"""Capture sources behind one small interface, named by URL (in rigs and on the command line).

Like python-can's ``BusABC`` and pyserial's ``serial_for_url``: one scheme, one module, one
class, imported lazily from :data:`SOURCES`; :func:`open_source` is the one door in. Sources
that live outside this package register through the ``dualhuman_builder.sources`` entry-point
group (as python-can's ``can.interface`` plugins do): ``sim://`` is registered that way by
:mod:`dualhuman_builder.sim.source`, so capture never imports the simulator.

==============================================  =================================================
``mvn+udp://HOST:9763[?allow=IP,IP]``           Xsens MVN network stream (:mod:`.mvn_udp`)
``vive+udp://HOST:8051[?allow=IP,IP]``          VIVE tracker bridge datagrams (:mod:`.vive_udp`)
``xbus:///dev/ttyUSB0?baud=921600``             Xsens MTi over serial; also ``xbus://loop`` and
                                                pty paths (:mod:`.xbus_serial`)
``mti+can://INTERFACE/CHANNEL``                 MTi-600 over CAN via python-can (:mod:`.mti_can`)
``vive+usb://[?serial=...]``                    VIVE tracker IMU over USB HID (:mod:`.vive_usb`)
``sim://TYPE?seed=N``                           simulated studio (registered by :mod:`dualhuman_builder.sim`)
==============================================  =================================================

Two layers, so that a recording can be replayed bit for bit:

* a :class:`Source` owns the transport. :meth:`Source.read` returns the :class:`RawPacket` s that
  arrived — each exactly what one transport read delivered (one UDP datagram, one serial read,
  one CAN frame as a 16-byte SocketCAN ``can_frame``) stamped with the host's monotonic clock;
* a :class:`Decoder` turns those packets into typed samples (:mod:`.samples`). It holds all the
  protocol state (reassembly, resynchronisation, grouping, loss counters) and is deterministic:
  the same packets in the same order give the same samples, which is what replay relies on
  (:meth:`Source.make_decoder` builds one from the URL without opening any device).

Bad input never raises out of a decoder: a corrupt, truncated, duplicated or unknown packet is
counted in :attr:`Decoder.counters` (and, when a person should know, logged in
:attr:`Decoder.events`), and decoding goes on with the next packet. One guard in :class:`Decoder`
holds every decoder to that, whatever its code does: the ``feed``, ``finish`` and ``status`` a
subclass defines are wrapped when the class is created (``__init_subclass__``), so an exception
inside them is counted (``decoder_errors``), reported as a ``decoder-error`` event (exception type,
short message and where it was raised, no traceback), the decoder's partial state is dropped
(:meth:`Decoder.recover`), and the call returns nothing (``[]``, ``{}``) — the packet that hit the
fault is lost, the next one is decoded. Events are coalesced per ``(kind, entity)``
(:meth:`Decoder.event`), so a flood of them keeps memory bounded for a whole take.
"""

from __future__ import annotations

import abc
import functools
import functools
import importlib
import importlib.metadata
import os
import time
import types
from collections import Counter
from dataclasses import dataclass
from typing import Any, Iterator
from urllib.parse import SplitResult, parse_qsl, urlsplit

from dualhuman_builder.errors import DualhumanError


class SourceError(DualhumanError):
    """A source URL that cannot be opened (unknown scheme, bad parameter, device absent)."""


class SourceLost(SourceError):
    """A device went away while it was being read (unplugged, port closed, bus down).

    Raised by :meth:`Source.read`; the recorder stops the take cleanly and keeps what it has."""


@dataclass(frozen=True, slots=True)
class RawPacket:
    """What one transport read delivered, as it arrived.

    ``host_time_ns``: ``time.monotonic_ns()`` when the read returned (int, ns); ``data``: the
    bytes — one UDP datagram, one serial read (any chunking), one CAN frame as a 16-byte SocketCAN
    ``struct can_frame`` (:func:`dualhuman_builder.capture.wire.mti_can.pack_can_frame`), one USB
    HID report."""

    host_time_ns: int
    data: bytes


@dataclass(frozen=True, slots=True)
class SourceEvent:
    """Something a person should hear about: ``kind`` (a short slug such as ``stale``,
    ``segment-count-changed``, ``resync``), ``entity`` (``mvn/1``, ``vive/LHR-...``, or the
    source), a human ``message``, and the host time it happened."""

    host_time_ns: int
    kind: str
    entity: str
    message: str


#: Events of one ``(kind, entity)`` a decoder keeps as they come before it coalesces them.
EVENT_BURST = 10
#: After the burst, at most one event of a ``(kind, entity)`` is kept per this much host time (ns);
#: it says how many like it were left out since the last one kept.
EVENT_INTERVAL_NS = 10_000_000_000
#: Most ``(kind, entity)`` pairs a decoder keeps apart; events of further pairs are coalesced together.
MAX_EVENT_KEYS = 1024
#: Most events a decoder holds until :meth:`Decoder.pop_events` drains them; more are counted
#: ``events_dropped`` (replay and other readers that never drain them stay bounded).
MAX_HELD_EVENTS = 10_000
#: Longest event message kept (characters); longer ones are cut.
MAX_EVENT_MESSAGE = 400
#: Where events of the pairs beyond :data:`MAX_EVENT_KEYS` are counted.
_OVERFLOW = ("", "")


def _short(text: str, limit: int = MAX_EVENT_MESSAGE) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."


class _EventKey:
    """Coalescing state of one ``(kind, entity)``: events kept, host time of the last kept one,
    events left out since, and the last one left out (for the summary at :meth:`Decoder.finish`)."""

    __slots__ = ("kept", "last_kept_ns", "suppressed", "last")

    def __init__(self) -> None:
        self.kept = 0
        self.last_kept_ns = 0
        self.suppressed = 0
        self.last: SourceEvent | None = None


class Decoder(abc.ABC):
    """Raw packets of one source -> typed samples. Deterministic and never raises on bad input.

    ``counters``: named counts, always at least ``packets``, ``bytes`` and ``samples``; the
    device-specific ones (``lost``, ``duplicate``, ``out_of_order``, ``bad_checksum``,
    ``truncated``, ``unknown_id``, ...) are documented by each decoder. ``events``: notable things
    in order (drained by whoever shows them: :meth:`pop_events`).

    The guard (see the module docstring): ``feed``, ``finish`` and ``status`` of every subclass
    never raise an :class:`Exception`. One that escapes a subclass's code is counted
    ``decoder_errors``, becomes a ``decoder-error`` event (entity: the decoder's ``device`` if it
    has one, else its class name) and calls :meth:`recover`; ``feed`` and ``finish`` then return
    ``[]``, ``status`` ``{}``. ``feed`` returning something other than a list is turned into one.
    Counters the guard and :meth:`event` add: ``decoder_errors``, ``events_suppressed``,
    ``events_dropped`` (present only once they happen)."""

    def __init__(self) -> None:
        self.counters: Counter = Counter()
        self.events: list[SourceEvent] = []
        self._event_keys: dict[tuple[str, str], _EventKey] = {}
        self._guard_host_ns = 0

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        for name, guard in (("feed", _guard_feed), ("finish", _guard_finish), ("status", _guard_status)):
            fn = cls.__dict__.get(name)
            if isinstance(fn, types.FunctionType) and not getattr(fn, "_decoder_guard", False):
                setattr(cls, name, guard(fn))

    @abc.abstractmethod
    def feed(self, packet: RawPacket) -> list:
        """Decode one packet; returns the samples it completed (maybe none)."""

    def finish(self) -> list:
        """End of the stream: the samples still held back, if any are complete enough to keep."""
        return []

    def status(self, now_ns: int) -> dict[str, dict[str, Any]]:
        """Liveness per entity (character, tracker, device) at host time ``now_ns``: a dict per
        entity with at least ``last_ns`` (host time of its last sample) and ``live`` (bool)."""
        return {}

    def recover(self) -> None:
        """Called by the guard after an exception escaped ``feed``, ``finish`` or ``status``:
        drop the partial state (a half-received frame, a group being assembled) so that the next
        packet starts clean. Counters, sequence tracking and settings stay. Default: nothing."""


    def event(self, host_time_ns: int, kind: str, entity: str, message: str) -> None:
        """Log an event for a person. Coalesced per ``(kind, entity)`` so that memory stays
        bounded however many come: the first :data:`EVENT_BURST` are kept as they are; after that
        at most one per :data:`EVENT_INTERVAL_NS` of host time is kept, its message followed by
        how many like it were left out since the last one kept (each counted
        ``events_suppressed``); :meth:`finish` adds one summary per pair with some still left
        out. Pairs beyond :data:`MAX_EVENT_KEYS` share one such budget; messages are cut at
        :data:`MAX_EVENT_MESSAGE` characters; beyond :data:`MAX_HELD_EVENTS` undrained events,
        new ones are only counted ``events_dropped``."""
        t = int(host_time_ns)
        ev = SourceEvent(t, str(kind), str(entity), _short(str(message)))
        keys = self._event_keys
        key = (ev.kind, ev.entity)
        st = keys.get(key)
        if st is None:
            if len(keys) >= MAX_EVENT_KEYS:
                key = _OVERFLOW
                st = keys.get(key)
            if st is None:
                st = keys[key] = _EventKey()
        if st.kept < EVENT_BURST or t - st.last_kept_ns >= EVENT_INTERVAL_NS:
            if st.kept >= EVENT_BURST and st.suppressed:
                others = " of other kinds or entities" if key is _OVERFLOW else " like it"
                ev = SourceEvent(t, ev.kind, ev.entity, _short(ev.message, MAX_EVENT_MESSAGE - 80)
                                 + f" ({st.suppressed} more{others} left out since the last one kept)")  # fmt: skip
            st.kept += 1
            st.last_kept_ns, st.suppressed, st.last = t, 0, None
            self._hold(ev)
        else:
            st.suppressed += 1
            st.last = ev
            self.counters["events_suppressed"] += 1

    def _hold(self, ev: SourceEvent) -> None:
        if len(self.events) >= MAX_HELD_EVENTS:
            self.counters["events_dropped"] += 1
        else:
            self.events.append(ev)

    def _flush_events(self) -> None:
        """One summary event per ``(kind, entity)`` with events left out since its last kept one."""
        for key, st in self._event_keys.items():
            if st.suppressed and st.last is not None:
                last, n = st.last, st.suppressed
                others = " of other kinds or entities" if key is _OVERFLOW else " like it"
                self._hold(SourceEvent(last.host_time_ns, last.kind, last.entity,
                                       f"{n} more event(s){others} left out; the last: {last.message}"))  # fmt: skip
                st.suppressed, st.last, st.last_kept_ns = 0, None, last.host_time_ns

    def pop_events(self) -> list[SourceEvent]:
        out, self.events = self.events, []
        return out

    def _decoder_error(self, where: str, error: Exception, host_ns: int) -> None:
        """The guard's handler: count, report and recover; never raises."""
        try:
            self.counters["decoder_errors"] += 1
        except Exception:  # noqa: BLE001 - a subclass's counters may be what failed
            pass
        try:
            tb = error.__traceback__
            while tb is not None and tb.tb_next is not None:
                tb = tb.tb_next
            at = f" at {os.path.basename(tb.tb_frame.f_code.co_filename)}:{tb.tb_lineno}" if tb is not None else ""
            entity = str(getattr(self, "device", "") or type(self).__name__)
            self.event(host_ns, "decoder-error", entity,
                       f"{type(self).__name__}.{where} raised {type(error).__name__}{at}: {_short(str(error), 200)}; "
                       "counted decoder_errors, decoding goes on with the next packet")  # fmt: skip
        except Exception:  # noqa: BLE001
            pass
        try:
            self.recover()
        except Exception:  # noqa: BLE001 - the next packet will tell
            pass


def _guard_feed(feed):
    @functools.wraps(feed)
    def guarded(self, packet):
        try:
            self._guard_host_ns = packet.host_time_ns
            out = feed(self, packet)
            return out if type(out) is list else ([] if out is None else list(out))
        except Exception as e:  # noqa: BLE001 - the guard: a decoder never raises
            self._decoder_error("feed", e, getattr(self, "_guard_host_ns", 0))
            return []

    guarded._decoder_guard = True
    return guarded


def _guard_finish(finish):
    @functools.wraps(finish)
    def guarded(self):
        try:
            out = finish(self)
            out = out if type(out) is list else ([] if out is None else list(out))
        except Exception as e:  # noqa: BLE001
            self._decoder_error("finish", e, getattr(self, "_guard_host_ns", 0))
            out = []
        try:
            self._flush_events()
        except Exception:  # noqa: BLE001
            pass
        return out

    guarded._decoder_guard = True
    return guarded


def _guard_status(status):
    @functools.wraps(status)
    def guarded(self, now_ns):
        try:
            out = status(self, now_ns)
            return out if isinstance(out, dict) else {}
        except Exception as e:  # noqa: BLE001
            self._decoder_error("status", e, now_ns)
            return {}

    guarded._decoder_guard = True
    return guarded


Decoder.finish = _guard_finish(Decoder.finish)


def rate_limited(quiet: dict, key, now_ns: int, interval_ns: int, message: str) -> str | None:
    """``message`` if an event under ``key`` may be emitted at host time ``now_ns`` (none in the
    last ``interval_ns``), with how many were held back since appended; else None, counted in
    ``quiet`` (the caller's per-entity ``{key: (last_ns, suppressed)}``). For a decoder's own
    per-entity limits, finer than :meth:`Decoder.event`'s coalescing."""
    last, suppressed = quiet.get(key, (None, 0))
    if last is not None and now_ns - last < interval_ns:
        quiet[key] = (last, suppressed + 1)
        return None
    quiet[key] = (now_ns, 0)
    return message + (f" ({suppressed} more since the last such event, counted only)" if suppressed else "")


class Source(abc.ABC):
    """A device (or a simulated one) named by ``url``. Iterate for samples, or :meth:`read`
    raw packets and feed them to :attr:`decoder` yourself (what the recorder does).

    Subclasses set :attr:`kind` (``mvn``, ``vive``, ``xbus``, ``mti-can``, ``vive-usb``,
    ``sim``) and :data:`PARAMS` (the URL query parameters they accept), open the transport in
    ``__init__`` (raising :class:`SourceError` with a fix when they cannot), and implement
    :meth:`read` and :meth:`make_decoder`."""

    kind: str = ""
    PARAMS: tuple[str, ...] = ()
    #: True for a URL that stands for a whole studio (``sim://``): recording it opens
    #: :meth:`loopback_studio` (every device on its own transport) rather than this one source.
    PLAYS_STUDIO: bool = False

    def __init__(self, url: str):
        self.url = url
        #: Transport-level counts (``rejected_senders``, ``kernel_drops``, ...).
        self.counters: Counter = Counter()
        self.decoder: Decoder | None = None
        self.closed = False

    @abc.abstractmethod
    def read(self, timeout: float) -> list[RawPacket]:
        """What arrived within ``timeout`` seconds ([] if nothing), in arrival order. Raises
        :class:`SourceLost` when the device is gone; never for one bad packet."""

    @classmethod
    def make_decoder(cls, url: str) -> Decoder:
        """A fresh decoder for the packets of a source opened with ``url`` (used by replay)."""
        raise SourceError(f"{cls.__name__} has no decoder")

    @classmethod
    def loopback_studio(cls, url: str, *, speed: float = 1.0, faults=None, progress=None):
        """For :attr:`PLAYS_STUDIO` sources: the studio ``url`` names, played onto loopback
        transports and opened as live sources. Returns an object with ``sources`` (``[(name,
        Source)]``), ``actors`` (rig actors), ``rig_text``, ``finished()`` and ``close()``."""
        raise SourceError(f"{cls.__name__} is one device, not a studio to play")

    def stats(self) -> dict[str, int]:
        """Transport and decoder counters together."""
        out = dict(self.counters)
        if self.decoder is not None:
            out.update(self.decoder.counters)
        return out

    def __iter__(self) -> Iterator:
        """Samples as they arrive, until :meth:`close` (or the device is lost: SourceLost)."""
        if self.decoder is None:
            self.decoder = self.make_decoder(self.url)
        while not self.closed:
            for packet in self.read(0.1):
                yield from self.decoder.feed(packet)
        yield from self.decoder.finish()

    def close(self) -> None:
        self.closed = True

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def now_ns() -> int:
    """The host clock every sample is stamped with: ``time.monotonic_ns()``."""
    return time.monotonic_ns()


def parse_source_url(url: str, params: tuple[str, ...]) -> tuple[SplitResult, dict[str, str]]:
    """Split ``url``; its query as a dict. Unknown or repeated parameters raise SourceError."""
    parts = urlsplit(url)
    pairs = parse_qsl(parts.query, keep_blank_values=True)
    query = dict(pairs)
    if len(query) != len(pairs):
        raise SourceError(f"a parameter is given twice in {url!r}")
    unknown = sorted(set(query) - set(params))
    if unknown:
        raise SourceError(f"unknown {parts.scheme}:// parameter(s) {', '.join(unknown)} in {url!r}",
                          fix=f"use only {', '.join(params) or 'no parameters'}")  # fmt: skip
    return parts, query


def number_param(query: dict, key: str, kind, default):
    """``query[key]`` as ``kind`` (int or float), ``default`` when absent; SourceError if not a number."""
    if key not in query:
        return default
    try:
        return kind(query[key])
    except ValueError:
        raise SourceError(f"{key}={query[key]!r} is not a{'n' if kind is int else ''} {kind.__name__}",
                          fix=f"give {key} as a number") from None  # fmt: skip


#: Scheme -> "module:Class" of the sources built into capture (imported when first used, like
#: python-can's interface table).
SOURCES: dict[str, str] = {
    "mvn+udp": "dualhuman_builder.capture.mvn_udp:MvnUdpSource",
    "vive+udp": "dualhuman_builder.capture.vive_udp:ViveUdpSource",
    "xbus": "dualhuman_builder.capture.xbus_serial:XbusSource",
    "mti+can": "dualhuman_builder.capture.mti_can:MtiCanSource",
    "vive+usb": "dualhuman_builder.capture.vive_usb:ViveUsbSource",
}
#: Entry-point group of sources registered from outside capture (``name = "module:Class"``).
ENTRY_POINT_GROUP = "dualhuman_builder.sources"


def registered_sources() -> dict[str, str]:
    """Every scheme a source URL may use -> ``"module:Class"``: :data:`SOURCES` plus the
    :data:`ENTRY_POINT_GROUP` entry points of the installed packages (scanned once per process:
    the scan reads every installed distribution's metadata, ~10 ms, and replay and repair build a
    decoder per source)."""
    return {**SOURCES, **{k: v for k, v in _entry_point_sources().items() if k not in SOURCES}}


@functools.cache
def _entry_point_sources() -> dict[str, str]:
    out: dict[str, str] = {}
    for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP):
        out.setdefault(ep.name, ep.value)
    return out


def source_class(url: str) -> type[Source]:
    """The :class:`Source` subclass that handles ``url``'s scheme."""
    scheme = urlsplit(url).scheme
    known = registered_sources()
    if scheme not in known:
        raise SourceError(f"unknown source scheme {scheme!r} in {url!r}",
                          fix=f"use one of {', '.join(s + '://' for s in known)}")  # fmt: skip
    module, _, name = known[scheme].partition(":")
    return getattr(importlib.import_module(module), name)


def open_source(url: str, **kwargs) -> Source:
    """Open the source ``url`` names (see the module docstring for the schemes)."""
    return source_class(url)(url, **kwargs)


def make_decoder(url: str) -> Decoder:
    """A fresh decoder for packets recorded from ``url`` (no device is opened)."""
    return source_class(url).make_decoder(url)


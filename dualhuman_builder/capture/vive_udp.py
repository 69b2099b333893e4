"""``vive+udp://HOST:8051[?allow=IP,IP&rcvbuf=BYTES&stale=S&serials=A,B]``: VIVE tracker poses
from a bridge (OpenVR or libsurvive), one 128-byte datagram per pose
(:mod:`dualhuman_builder.capture.wire.vive_udp`). Many trackers share one port and differ by
serial.

Parameters: ``allow`` and ``rcvbuf`` as every UDP source (:mod:`.udp`); ``stale`` seconds
without a sample before a tracker is reported not live (default 0.5); ``serials`` a
comma-separated list of the trackers to keep (default: all). A studio names both: ``allow`` keeps
other machines out, ``serials`` other trackers (``dualhuman rig check`` warns when either is
missing).

:class:`ViveUdpDecoder` yields :class:`~dualhuman_builder.capture.samples.TrackerSample` s in
our world frame (Y-up, metres, quaternion x, y, z, w) with the bridge's device time and the
host receive time (int ns). Tracking loss reaches the pipeline as ``valid=False`` whichever way
the tracker reports it: the pose-valid flag clear, or OpenVR's jump of a "valid" pose to exactly
(0, 0, 0) (both seen from OpenVR: ``TriadSemi/triad_openvr`` issue 16).

Tracker table: state is kept for at most :data:`MAX_TRACKERS` serials. A tracker is *established*
once listed in ``serials=`` or after :data:`ESTABLISHED` samples. When a new serial finds the
table full, the newcomer heard from longest ago (not yet established) makes room, else the
established tracker silent for longest if it has been silent over ``stale`` seconds
(``evicted_trackers``); if none can, the new serial is dropped (``too_many_trackers``). The first
time the table is full, one ``tracker-table-full`` event (entity ``vive``) says so. A flood of
invented serials thus cannot lock out a tracker that is sending.

Device-time sequence, per tracker: a sample whose device time is within :data:`SEQUENCE_NS` of
the tracker's newest, either way, is in sequence (older: ``out_of_order``, still yielded). Any
other is held back, neither yielded nor allowed to move the newest: held samples within
:data:`SEQUENCE_NS` of each other form a candidate (at most :data:`MAX_CANDIDATES` per tracker),
dropped as ``out_of_sequence`` when the tracker's own stream moves forward first. A candidate that
reaches :data:`CONFIRM` samples is the stream now and its samples are yielded: a forward jump no
larger than the host time that passed (plus :data:`SEQUENCE_NS`) is a pause, anything else a reset
of the bridge's clock (``clock_resets``, event ``clock-reset``). A single stray datagram with a
far-off device time is therefore dropped and counted, and never makes the real samples that follow
look out of order.

Events (entity ``vive/<serial>``) are for established trackers only, and each kind comes at most
once per :data:`EVENT_INTERVAL_NS` of host time per tracker (those in between are counted, and the
next event says how many): ``other-serial`` (once per ignored serial, up to :data:`MAX_TRACKERS`),
``disconnected`` / ``connected`` (the device-connected flag changed and held for :data:`CONFIRM`
samples), ``stale`` (no sample for ``stale_s``: from :meth:`ViveUdpDecoder.status`, or from
:meth:`ViveUdpDecoder.feed` when the gap is seen first there), ``resumed`` and ``clock-reset``.
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict, deque

from dualhuman_builder.capture.samples import TrackerSample
from dualhuman_builder.capture.sources import (Decoder, RawPacket, SourceError, number_param, parse_source_url,
                                               rate_limited)  # fmt: skip
from dualhuman_builder.capture.udp import UdpSource
from dualhuman_builder.capture.wire.vive_udp import (DEFAULT_PORT, ViveFormatError, datagram_connected,
                                                     decode_tracker)  # fmt: skip

DEFAULT_STALE_S = 0.5
#: Device times remembered per tracker to recognise a duplicate that arrives late.
DUPLICATE_WINDOW = 64
#: Arrivals per tracker over which ``rate_hz`` is measured.
RATE_WINDOW = 50
#: Most distinct trackers (and distinct ignored serials) one decoder keeps state for, so that
#: garbage serials cannot grow it without bound.
MAX_TRACKERS = 256
#: Samples after which a tracker not listed in ``serials=`` is established (keeps its place in a
#: full table, gets events).
ESTABLISHED = 8
#: Largest step of a tracker's device time, either way, taken as in sequence (ns).
SEQUENCE_NS = 500_000_000
#: Held samples that confirm a candidate (and connected-flag samples that confirm a change), and
#: most candidates held per tracker.
CONFIRM = 4
MAX_CANDIDATES = 2
#: Host ns between two events of one kind for one tracker.
EVENT_INTERVAL_NS = 1_000_000_000


class _Held:
    """A candidate: out-of-sequence samples of one tracker within SEQUENCE_NS of each other, as
    ``(sample, connected, host ns)`` in arrival order."""

    __slots__ = ("items", "times", "lo", "hi", "last")

    def __init__(self) -> None:
        self.items: list[tuple[TrackerSample, bool, int]] = []
        self.times: set[int] = set()
        self.lo = self.hi = self.last = 0

    def follows(self, t: int) -> bool:
        return self.lo - SEQUENCE_NS <= t <= self.hi + SEQUENCE_NS

    def add(self, sample: TrackerSample, connected: bool, host: int, arrival: int) -> None:
        t = sample.device_time_ns
        if not self.items:
            self.lo = self.hi = t
        self.items.append((sample, connected, host))
        self.times.add(t)
        self.lo, self.hi, self.last = min(self.lo, t), max(self.hi, t), arrival


class _Tracker:
    __slots__ = ("last_device_ns", "newest_host_ns", "recent", "recent_set", "last_host_ns", "arrivals", "valid",
                 "connected", "flag_run", "stale", "samples", "listed", "held", "held_arrivals", "quiet")  # fmt: skip

    def __init__(self, listed: bool) -> None:
        self.last_device_ns: int | None = None  # newest in-sequence device time
        self.newest_host_ns = 0  # host time that sample arrived
        self.recent: deque[int] = deque()
        self.recent_set: set[int] = set()
        self.last_host_ns: int | None = None
        self.arrivals: deque[int] = deque(maxlen=RATE_WINDOW)
        self.valid = False
        self.connected = True  # the connected flag as reported (changes once it holds for CONFIRM samples)
        self.flag_run = 0  # samples in a row whose flag differs from ``connected``
        self.stale = False
        self.samples = 0  # yielded
        self.listed = listed
        self.held: list[_Held] = []
        self.held_arrivals = 0
        self.quiet: dict[str, tuple[int, int]] = {}  # event kind -> (host ns of the last emitted, suppressed since)

    @property
    def established(self) -> bool:
        return self.listed or self.samples >= ESTABLISHED


class ViveUdpDecoder(Decoder):
    """Tracker datagrams -> :class:`~dualhuman_builder.capture.samples.TrackerSample` s, one per new pose.

    ``stale_s``: seconds without a sample after which a tracker is not live; ``serials``: keep
    only these trackers (None: all). The tracker table, the device-time sequence and the events
    are described in the module docstring.

    Counters: ``packets``, ``bytes``, ``samples`` (yielded); malformed datagrams, dropped:
    ``truncated`` (< 128 bytes), ``bad_length`` (> 128), ``bad_magic``, ``bad_version``,
    ``bad_field`` (reserved bits/bytes set, bad serial), ``bad_pose`` (a pose flagged valid with
    NaN/inf or a non-unit quaternion); stream: ``duplicate`` (same serial and device time as one
    of the last 64 seen, or as a held one: dropped), ``out_of_order`` (device time older than that
    tracker's newest: yielded), ``out_of_sequence`` (held, then dropped), ``clock_resets``,
    ``invalid_pose`` (pose-valid flag clear: yielded with ``valid=False``), ``jumps_to_origin`` (a
    valid-flagged pose at exactly (0, 0, 0): yielded with ``valid=False``), ``disconnected``
    (device-connected flag clear: yielded with ``valid=False``), ``other_serial`` (a tracker not
    in ``serials``: dropped), ``evicted_trackers`` (made room in a full table),
    ``too_many_trackers`` (a new serial the full table had no room for: dropped).
    """

    def __init__(self, stale_s: float = DEFAULT_STALE_S, serials=None):
        super().__init__()
        if not stale_s > 0:
            raise ValueError(f"stale_s must be positive, got {stale_s}")
        self.stale_ns = int(round(stale_s * 1e9))
        self.serials = frozenset(serials) if serials else None
        self.trackers: dict[str, _Tracker] = {}
        self._newcomers: OrderedDict[str, _Tracker] = OrderedDict()  # not yet established, least recently heard first
        self._ignored: set[str] = set()
        self._table_full_reported = False

    def feed(self, packet: RawPacket) -> list:
        c = self.counters
        c["packets"] += 1
        c["bytes"] += len(packet.data)
        try:
            sample = decode_tracker(packet.data, packet.host_time_ns)
        except ViveFormatError as e:
            c[e.counter] += 1
            return []
        serial, host = sample.serial, packet.host_time_ns
        if self.serials is not None and serial not in self.serials:
            c["other_serial"] += 1
            if serial not in self._ignored and len(self._ignored) < MAX_TRACKERS:
                self._ignored.add(serial)
                listed = ", ".join(sorted(self.serials))
                self.event(host, "other-serial", f"vive/{serial}",
                           f"tracker {serial} is not in serials= ({listed}); dropped")  # fmt: skip
            return []
        tr = self.trackers.get(serial)
        if tr is None:
            if len(self.trackers) >= MAX_TRACKERS and not self._make_room(host):
                c["too_many_trackers"] += 1
                return []
            tr = self.trackers[serial] = _Tracker(listed=self.serials is not None)
            if not tr.listed:
                self._newcomers[serial] = tr
        connected = datagram_connected(packet.data)
        t, newest = sample.device_time_ns, tr.last_device_ns
        if newest is not None and not newest - SEQUENCE_NS <= t <= newest + SEQUENCE_NS:
            return self._hold_sample(serial, tr, sample, connected, host)
        if newest is not None and t > newest and tr.held:  # the tracker's stream went on: what was held was not it
            self._drop_held(tr)
        return self._take(serial, tr, sample, connected, host)

    def finish(self) -> list:
        """End of the stream: samples still held out of sequence are counted ``out_of_sequence``."""
        for tr in self.trackers.values():
            self._drop_held(tr)
        return []

    def recover(self) -> None:
        """After a fault the decoder did not foresee: drop the held samples (``out_of_sequence``)."""
        for tr in self.trackers.values():
            self._drop_held(tr)

    # ------------------------------------------------------------------------------ internals
    def _make_room(self, now: int) -> bool:
        """Evict one tracker from the full table (module docstring); False if none may go."""
        if self._newcomers:
            serial, _ = self._newcomers.popitem(last=False)
        else:
            silent = [(tr.last_host_ns if tr.last_host_ns is not None else -(1 << 62), s)
                      for s, tr in self.trackers.items()
                      if tr.last_host_ns is None or now - tr.last_host_ns > self.stale_ns]  # fmt: skip
            serial = min(silent)[1] if silent else None
        if not self._table_full_reported:
            self._table_full_reported = True
            self.event(now, "tracker-table-full", "vive",
                       f"{MAX_TRACKERS} tracker serials heard: a new one takes the place of a tracker heard fewer "
                       f"than {ESTABLISHED} times or silent for {self.stale_ns / 1e9:g} s, else it is dropped "
                       "(too_many_trackers); list the studio's trackers in serials=")  # fmt: skip
        if serial is None:
            return False
        self._drop_held(self.trackers.pop(serial))
        self.counters["evicted_trackers"] += 1
        return True

    def _hold_sample(self, serial: str, tr: _Tracker, sample: TrackerSample, connected: bool, host: int) -> list:
        """Keep an out-of-sequence sample with the candidate it follows; confirm that candidate once
        it holds CONFIRM samples."""
        t = sample.device_time_ns
        tr.held_arrivals += 1
        cand = next((h for h in tr.held if h.follows(t)), None)
        if cand is None:
            if len(tr.held) >= MAX_CANDIDATES:
                gone = min(tr.held, key=lambda h: h.last)
                tr.held.remove(gone)
                self.counters["out_of_sequence"] += len(gone.items)
            cand = _Held()
            tr.held.append(cand)
        elif t in cand.times:
            self.counters["duplicate"] += 1
            return []
        cand.add(sample, connected, host, tr.held_arrivals)
        if len(cand.items) < CONFIRM:
            return []
        tr.held.remove(cand)
        self._drop_held(tr)
        first = min(cand.items, key=lambda item: item[0].device_time_ns)
        step = cand.lo - tr.last_device_ns
        if not 0 < step <= first[2] - tr.newest_host_ns + SEQUENCE_NS:  # not a pause of the tracker
            self.counters["clock_resets"] += 1
            self._event_limited(tr, host, "clock-reset", f"vive/{serial}",
                                f"device time of tracker {serial} jumped by {step / 1e9:+.3f} s: its bridge restarted "
                                "its clock (or another sender uses this serial)")  # fmt: skip
        tr.last_device_ns = None
        tr.recent.clear()
        tr.recent_set.clear()
        out: list = []
        for s, conn, h in cand.items:
            out += self._take(serial, tr, s, conn, h)
        return out

    def _drop_held(self, tr: _Tracker) -> None:
        for h in tr.held:
            self.counters["out_of_sequence"] += len(h.items)
        tr.held = []

    def _event_limited(self, tr: _Tracker, now: int, kind: str, entity: str, message: str) -> None:
        """An event of ``kind`` for an established tracker, at most one per EVENT_INTERVAL_NS of host time."""
        if not tr.established:
            return
        message = rate_limited(tr.quiet, kind, now, EVENT_INTERVAL_NS, message)
        if message is not None:
            self.event(now, kind, entity, message)

    def _take(self, serial: str, tr: _Tracker, sample: TrackerSample, connected: bool, host: int) -> list:
        """An in-sequence sample: duplicates, order, flags, liveness; the sample to yield, if any."""
        c = self.counters
        t = sample.device_time_ns
        if t in tr.recent_set:
            c["duplicate"] += 1
            return []
        if tr.last_device_ns is not None and t < tr.last_device_ns:
            c["out_of_order"] += 1
        else:
            tr.last_device_ns, tr.newest_host_ns = t, host
        tr.recent.append(t)
        tr.recent_set.add(t)
        if len(tr.recent) > DUPLICATE_WINDOW:
            tr.recent_set.discard(tr.recent.popleft())

        if connected == tr.connected:
            tr.flag_run = 0
        else:
            tr.flag_run += 1
            if tr.flag_run >= CONFIRM:
                tr.connected, tr.flag_run = connected, 0
                what = "is connected again" if connected else "reports it is disconnected"
                self._event_limited(tr, host, "connected" if connected else "disconnected", f"vive/{serial}",
                                    f"tracker {serial} {what}")
        valid = sample.valid
        if not connected:
            c["disconnected"] += 1
            valid = False
        elif not valid:
            c["invalid_pose"] += 1
        elif not sample.position.any():  # exactly (0, 0, 0): OpenVR's tracking-loss symptom
            c["jumps_to_origin"] += 1
            valid = False
        if valid != sample.valid:
            sample = dataclasses.replace(sample, valid=False)

        if tr.last_host_ns is not None and host - tr.last_host_ns > self.stale_ns and not tr.stale:
            self._event_limited(tr, tr.last_host_ns + self.stale_ns, "stale", f"vive/{serial}",
                                f"no pose from tracker {serial} for {self.stale_ns / 1e9:g} s")
            tr.stale = True
        if tr.stale:
            self._event_limited(tr, host, "resumed", f"vive/{serial}",
                                f"tracker {serial} sends again after {(host - tr.last_host_ns) / 1e9:.3f} s")
            tr.stale = False
            tr.arrivals.clear()
        tr.last_host_ns = host
        tr.arrivals.append(host)
        tr.valid = valid
        tr.samples += 1
        if tr.samples <= ESTABLISHED and not tr.listed:
            if tr.samples == ESTABLISHED:
                self._newcomers.pop(serial, None)
            elif serial in self._newcomers:
                self._newcomers.move_to_end(serial)
        c["samples"] += 1
        return [sample]

    def status(self, now_ns: int) -> dict[str, dict]:
        """Per ``vive/<serial>``: ``last_ns`` (host time of its last sample), ``live`` (a sample
        within ``stale_s``), ``rate_hz`` (arrival rate over its last 50 samples, 0 when not
        live), ``valid`` (its last pose was valid), ``connected`` (its connected flag, as last
        confirmed). An established tracker first seen not live here gets a ``stale`` event."""
        out = {}
        for serial, tr in self.trackers.items():
            if tr.last_host_ns is None:
                continue
            live = now_ns - tr.last_host_ns <= self.stale_ns
            if not live and not tr.stale:
                tr.stale = True
                self._event_limited(tr, now_ns, "stale", f"vive/{serial}",
                                    f"no pose from tracker {serial} for {self.stale_ns / 1e9:g} s")
            rate = 0.0
            if live and len(tr.arrivals) >= 2 and tr.arrivals[-1] > tr.arrivals[0]:
                rate = (len(tr.arrivals) - 1) * 1e9 / (tr.arrivals[-1] - tr.arrivals[0])
            out[f"vive/{serial}"] = {"last_ns": tr.last_host_ns, "live": live, "rate_hz": rate, "valid": tr.valid,
                                     "connected": tr.connected}  # fmt: skip
        return out


def _decoder_options(url: str, params: tuple[str, ...]) -> dict:
    _, query = parse_source_url(url, params)
    stale = number_param(query, "stale", float, DEFAULT_STALE_S)
    if not stale > 0:
        raise SourceError(f"stale={query['stale']!r} in {url!r} must be a positive number of seconds")
    serials = None
    if "serials" in query:
        serials = [s.strip() for s in query["serials"].split(",") if s.strip()]
        if not serials:
            raise SourceError(f"serials= in {url!r} lists no tracker", fix="write serials=LHR-AAAA,LHR-BBBB")
    return {"stale_s": stale, "serials": serials}


class ViveUdpSource(UdpSource):
    """Receives the tracker bridge's datagrams on ``HOST:PORT`` (default 8051); see the module
    docstring for the URL and :class:`ViveUdpDecoder` for samples and counters."""

    kind = "vive"
    DEFAULT_PORT = DEFAULT_PORT
    PARAMS = ("allow", "rcvbuf", "stale", "serials")

    @classmethod
    def make_decoder(cls, url: str) -> ViveUdpDecoder:
        return ViveUdpDecoder(**_decoder_options(url, cls.PARAMS))

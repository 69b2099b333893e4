"""``vive+udp://HOST:8051[?allow=IP,IP&rcvbuf=BYTES&stale=S&serials=A,B]``: VIVE tracker poses
from a bridge (OpenVR or libsurvive), one 128-byte datagram per pose
(:mod:`dualhuman_builder.capture.wire.vive_udp`). Many trackers share one port and differ by
serial.

Parameters: ``allow`` and ``rcvbuf`` as every UDP source (:mod:`.udp`); ``stale`` seconds
without a sample before a tracker is reported not live (default 0.5); ``serials`` a
comma-separated list of the trackers to keep (default: all).

:class:`ViveUdpDecoder` yields :class:`~dualhuman_builder.capture.samples.TrackerSample` s in
our world frame (Y-up, metres, quaternion x, y, z, w) with the bridge's device time and the
host receive time (int ns). Tracking loss reaches the pipeline as ``valid=False`` whichever way
the tracker reports it: the pose-valid flag clear, or OpenVR's jump of a "valid" pose to exactly
(0, 0, 0) (both seen from OpenVR: ``TriadSemi/triad_openvr`` issue 16).
"""

from __future__ import annotations

import dataclasses
from collections import deque

from dualhuman_builder.capture.sources import Decoder, RawPacket, SourceError, number_param, parse_source_url
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


class _Tracker:
    __slots__ = ("last_device_ns", "recent", "recent_set", "last_host_ns", "arrivals", "valid", "connected",
                 "stale")  # fmt: skip

    def __init__(self) -> None:
        self.last_device_ns: int | None = None
        self.recent: deque[int] = deque()
        self.recent_set: set[int] = set()
        self.last_host_ns: int | None = None
        self.arrivals: deque[int] = deque(maxlen=RATE_WINDOW)
        self.valid = False
        self.connected = True
        self.stale = False


class ViveUdpDecoder(Decoder):
    """Tracker datagrams -> :class:`~dualhuman_builder.capture.samples.TrackerSample` s, one per new pose.

    ``stale_s``: seconds without a sample after which a tracker is not live; ``serials``: keep
    only these trackers (None: all).

    Counters: ``packets``, ``bytes``, ``samples`` (yielded); malformed datagrams, dropped:
    ``truncated`` (< 128 bytes), ``bad_length`` (> 128), ``bad_magic``, ``bad_version``,
    ``bad_field`` (reserved bits/bytes set, bad serial), ``bad_pose`` (a pose flagged valid with
    NaN/inf or a non-unit quaternion); stream: ``duplicate`` (same serial and device time as one
    of the last 64 seen: dropped), ``out_of_order`` (device time older than that tracker's newest:
    yielded), ``invalid_pose`` (pose-valid flag clear: yielded with ``valid=False``),
    ``jumps_to_origin`` (a valid-flagged pose at exactly (0, 0, 0): yielded with ``valid=False``),
    ``disconnected`` (device-connected flag clear: yielded with ``valid=False``), ``other_serial``
    (a tracker not in ``serials``: dropped), ``too_many_trackers`` (a new serial beyond
    :data:`MAX_TRACKERS`: dropped).

    Events (entity ``vive/<serial>``): ``other-serial`` (once per ignored serial), ``disconnected``
    / ``connected`` (flag changes), ``stale`` (no sample for ``stale_s``: from :meth:`status`, or
    from :meth:`feed` when the gap is seen first there) and ``resumed``.
    """

    def __init__(self, stale_s: float = DEFAULT_STALE_S, serials=None):
        super().__init__()
        if not stale_s > 0:
            raise ValueError(f"stale_s must be positive, got {stale_s}")
        self.stale_ns = int(round(stale_s * 1e9))
        self.serials = frozenset(serials) if serials else None
        self.trackers: dict[str, _Tracker] = {}
        self._ignored: set[str] = set()

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
        entity = f"vive/{serial}"
        if self.serials is not None and serial not in self.serials:
            c["other_serial"] += 1
            if serial not in self._ignored and len(self._ignored) < MAX_TRACKERS:
                self._ignored.add(serial)
                listed = ", ".join(sorted(self.serials))
                self.event(host, "other-serial", entity, f"tracker {serial} is not in serials= ({listed}); dropped")
            return []
        tr = self.trackers.get(serial)
        if tr is None:
            if len(self.trackers) >= MAX_TRACKERS:
                c["too_many_trackers"] += 1
                return []
            tr = self.trackers[serial] = _Tracker()
        t = sample.device_time_ns
        if t in tr.recent_set:
            c["duplicate"] += 1
            return []
        if tr.last_device_ns is not None and t < tr.last_device_ns:
            c["out_of_order"] += 1
        else:
            tr.last_device_ns = t
        tr.recent.append(t)
        tr.recent_set.add(t)
        if len(tr.recent) > DUPLICATE_WINDOW:
            tr.recent_set.discard(tr.recent.popleft())

        connected = datagram_connected(packet.data)
        if connected != tr.connected:
            self.event(host, "connected" if connected else "disconnected", entity,
                       f"tracker {serial} {'is connected again' if connected else 'reports it is disconnected'}")
            tr.connected = connected
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
            self.event(tr.last_host_ns + self.stale_ns, "stale", entity,
                       f"no pose from tracker {serial} for {self.stale_ns / 1e9:g} s")
            tr.stale = True
        if tr.stale:
            self.event(host, "resumed", entity,
                       f"tracker {serial} sends again after {(host - tr.last_host_ns) / 1e9:.3f} s")  # fmt: skip
            tr.stale = False
            tr.arrivals.clear()
        tr.last_host_ns = host
        tr.arrivals.append(host)
        tr.valid = valid
        c["samples"] += 1
        return [sample]

    def status(self, now_ns: int) -> dict[str, dict]:
        """Per ``vive/<serial>``: ``last_ns`` (host time of its last sample), ``live`` (a sample
        within ``stale_s``), ``rate_hz`` (arrival rate over its last 50 samples, 0 when not
        live), ``valid`` (its last pose was valid), ``connected`` (its last connected flag).
        A tracker first seen not live here gets a ``stale`` event."""
        out = {}
        for serial, tr in self.trackers.items():
            if tr.last_host_ns is None:
                continue
            live = now_ns - tr.last_host_ns <= self.stale_ns
            if not live and not tr.stale:
                tr.stale = True
                self.event(now_ns, "stale", f"vive/{serial}",
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

"""``mvn+udp://HOST:PORT[?allow=IP,IP&rcvbuf=BYTES&stale=S&characters=0,1]``: the Xsens MVN
real-time network stream (:mod:`~dualhuman_builder.capture.wire.mvn` for the bytes).

URL parameters: ``allow`` and ``rcvbuf`` as every UDP source (:mod:`.udp`); ``stale``: seconds
without a sample after which a character is reported not live (default 0.5); ``characters``:
the character IDs to keep (comma-separated, default all).

:class:`MvnDecoder` turns datagrams into typed samples:

====  ===========================================  =====================================
type  message                                      sample (:mod:`.samples`)
====  ===========================================  =====================================
02    pose, quaternions                            :class:`~.samples.SuitFrame`
12    meta data (``name``, ``xmid``, ``color``)    :class:`~.samples.SuitMeta`
13    scale (null-pose segment origins, points)    :class:`~.samples.SuitScale`
20    joint angles                                 :class:`~.samples.JointAngles`
21    linear segment kinematics                    :class:`~.samples.LinearSegmentKinematics`
22    angular segment kinematics                   :class:`~.samples.AngularSegmentKinematics`
24    centre of mass                               :class:`~.samples.CenterOfMass`
25    time code ``HH:MM:SS.mmm``                   :class:`~.samples.SuitTimeCode`
====  ===========================================  =====================================

Types 01, 03, 04, 05, 10, 11, 23 (and any other) are counted ``unsupported_type``, one event
per type. Every sample keeps ``host_time_ns`` — the host time of the datagram that completed its
message — and ``device_time_ns = time_code_ms * 1_000_000``: the wire carries no other device
clock than MVN's recording clock in ms (so a simulated suit's ``device_time_ns``, which includes
its clock offset, arrives as the time code: ms since its first sample, floored).

Reassembly: datagrams of one message share (character, message type, sample counter) and are
joined by their 7-bit piece index once the last-piece bit has been seen and every index up to it
is present. A message still incomplete when a message of the same character and type more than
:data:`WINDOW` sample counters newer completes is dropped (``incomplete``, also at
:meth:`~MvnDecoder.finish`); at most :data:`MAX_PENDING` messages
and :data:`MAX_PENDING_BYTES` bytes wait (the oldest is dropped first: ``evicted``).

Characters: several actors share one port and differ only in the character-ID byte; each is its
own stream (:attr:`SuitFrame.character`) with its own counters in :attr:`MvnDecoder.characters`.
The u32 sample counter and the u32 time code are unwrapped per character (a signed 32-bit step
from the newest value seen), so ``sample_counter``, ``time_code_ms`` and ``device_time_ns`` stay
monotonic across a wrap. From the type-02 sample counters of each character:

* ``lost``: counters skipped (a gap) between the oldest and newest seen; a late arrival takes its
  counter back out (loss at the very end of a stream is not seen);
* ``out_of_order``: a counter older than the newest seen that had not arrived yet (yielded);
* ``duplicate``: a datagram received before (a piece of a message still waiting, or any datagram
  of a message decoded among the last :data:`COMPLETED_MEMORY`), or a pose whose counter was
  already yielded; never yielded twice;
* a counter more than :data:`SEEN_WINDOW` behind the newest, or more than :data:`RESET_GAP`
  ahead, is MVN restarting its counter (``counter_resets``, event ``counter-reset``), not loss.

Liveness: a character is live from its first sample until it has sent nothing for ``stale``
seconds of host time; going stale emits ``stale`` (noticed by the next datagram of any character,
checked at most every :data:`STALE_CHECK_NS`, or by :meth:`MvnDecoder.status`), its next sample
``resumed``. A change of a character's pose layout (number of segments, props or finger segments:
MVN recomposed the scene) emits ``segment-count-changed``; decoding goes on with the new layout.

MVN datagrams carry no checksum: corruption is caught only where it breaks the layout (ID string,
sizes, item counts, strings, non-finite values, quaternion norms); a flipped bit in a position or
in a counter goes through as a wrong value.

Counters (:attr:`Decoder.counters`): ``packets``, ``bytes``, ``samples`` (all types), ``frames``
(type 02), ``truncated`` (shorter than the header or than its payload-size field says),
``bad_header`` (ID string, payload size shorter than the datagram, inconsistent piece indices),
``bad_payload`` (a complete message that does not decode), ``incomplete``, ``evicted``, ``lost``,
``duplicate``, ``out_of_order``, ``counter_resets``, ``unsupported_type``, ``other_character``
(datagrams of characters not in ``characters=``), ``segment_count_changes``. Events: ``stale``,
``resumed``, ``segment-count-changed``, ``counter-reset`` (entity ``mvn/<character>``),
``unsupported-type`` and ``other-character`` (entity ``mvn``).
"""

from __future__ import annotations

import math
from collections import deque
from typing import Any, Iterable

import numpy as np

from dualhuman_builder.capture.samples import (AngularSegmentKinematics, CenterOfMass, JointAngles,
                                               LinearSegmentKinematics, SuitFrame, SuitMeta, SuitScale,
                                               SuitTimeCode)  # fmt: skip
from dualhuman_builder.capture.sources import Decoder, RawPacket, SourceError, number_param, parse_source_url
from dualhuman_builder.capture.udp import UdpSource
from dualhuman_builder.capture.wire import mvn
from dualhuman_builder.capture.wire.mvn import LAST_PIECE, MvnFormatError, MvnMessageType, unpack_header

#: Seconds without a sample after which a character is not live (URL ``stale=``).
DEFAULT_STALE_S = 0.5
#: An incomplete message is dropped once a message this many sample counters newer (same
#: character and type) completes.
WINDOW = 8
#: Most messages waiting for pieces, and most bytes they may hold; beyond, the oldest is evicted.
MAX_PENDING = 64
MAX_PENDING_BYTES = 4 << 20
#: Completed messages remembered (per decoder) to recognise their duplicated datagrams.
COMPLETED_MEMORY = 4096
#: Pose sample counters remembered per character to tell duplicates from late arrivals.
SEEN_WINDOW = 1024
#: A forward jump of the sample counter larger than this is a restart of MVN's counter, not loss
#: (2^20 samples: over an hour at 240 Hz).
RESET_GAP = 1 << 20
#: Pose samples over which ``rate_hz`` is measured (device time code).
RATE_WINDOW = 64
#: Feeds look for stale characters at most this often (host ns); :meth:`MvnDecoder.status` always.
STALE_CHECK_NS = 10_000_000

SUPPORTED = frozenset({2, 12, 13, 20, 21, 22, 24, 25})
_U32 = 1 << 32
_HALF = 1 << 31


def _type_label(t: int) -> str:
    try:
        return f"{t:02d} ({MvnMessageType(t).name.lower().replace('_', ' ')})"
    except ValueError:
        return f"{t:02d} (unknown)"


class _Character:
    """One character's stream state (see :attr:`MvnDecoder.characters` for what is public)."""

    __slots__ = ("id", "entity", "samples", "frames", "lost", "duplicate", "out_of_order", "incomplete",
                 "counter_resets", "segments", "layout", "name", "last_ns", "live", "hi", "lo", "seen",
                 "sc_raw", "sc_u", "tc_raw", "tc_u", "rate_tc")  # fmt: skip

    def __init__(self, cid: int):
        self.id = cid
        self.entity = f"mvn/{cid}"
        self.samples = self.frames = self.lost = self.duplicate = self.out_of_order = 0
        self.incomplete = self.counter_resets = 0
        self.segments = 0  # segments of the last pose
        self.layout: tuple[int, int, int] | None = None  # (items, props, fingers) of the last pose
        self.name = ""
        self.last_ns: int | None = None
        self.live = False
        self.hi: int | None = None  # newest unwrapped pose counter
        self.lo = 0  # oldest pose counter since the stream (re)started
        self.seen: set[int] = set()
        self.sc_raw: int | None = None  # unwrapping references: newest raw value and its unwrapped value
        self.sc_u = 0
        self.tc_raw: int | None = None
        self.tc_u = 0
        self.rate_tc: deque[int] = deque(maxlen=RATE_WINDOW)

    def unwrap_counter(self, raw: int) -> int:
        if self.sc_raw is None:
            self.sc_raw, self.sc_u = raw, raw
            return raw
        u = self.sc_u + ((raw - self.sc_raw + _HALF) % _U32) - _HALF
        if u > self.sc_u:
            self.sc_raw, self.sc_u = raw, u
        return u

    def unwrap_time(self, raw: int) -> int:
        if self.tc_raw is None:
            self.tc_raw, self.tc_u = raw, raw
            return raw
        u = self.tc_u + ((raw - self.tc_raw + _HALF) % _U32) - _HALF
        if u > self.tc_u:
            self.tc_raw, self.tc_u = raw, u
        return u

    def rate_hz(self) -> float:
        tc = self.rate_tc
        if len(tc) < 2:
            return 0.0
        span = max(tc) - min(tc)
        return (len(tc) - 1) * 1000.0 / span if span > 0 else 0.0

    def stats(self) -> dict[str, Any]:
        return {"samples": self.samples, "frames": self.frames, "lost": self.lost, "duplicate": self.duplicate,
                "out_of_order": self.out_of_order, "incomplete": self.incomplete,
                "counter_resets": self.counter_resets, "segments": self.segments, "name": self.name,
                "last_ns": self.last_ns, "live": self.live, "rate_hz": self.rate_hz()}  # fmt: skip


class _Partial:
    """A message whose pieces are arriving: piece index -> (payload, items)."""

    __slots__ = ("pieces", "last", "nbytes", "head")

    def __init__(self):
        self.pieces: dict[int, tuple[bytes, int]] = {}
        self.last: int | None = None
        self.nbytes = 0
        self.head: tuple | None = None  # header of piece 0


class MvnDecoder(Decoder):
    """MVN datagrams -> :class:`SuitFrame` and the other MVN samples (see the module docstring
    for reassembly, characters, counters and events).

    ``stale_s``: seconds without a sample before a character is not live; ``characters``: IDs to
    keep (None: all). :attr:`characters` gives each character's counters; :meth:`status` its
    liveness. Deterministic: the same datagrams in the same order give the same samples."""

    def __init__(self, *, stale_s: float = DEFAULT_STALE_S, characters: Iterable[int] | None = None):
        super().__init__()
        if not (stale_s > 0 and math.isfinite(stale_s)):
            raise ValueError(f"stale_s must be a positive number of seconds, got {stale_s}")
        self.stale_ns = int(stale_s * 1e9)
        self.keep = None if characters is None else frozenset(int(c) for c in characters)
        self._chars: dict[int, _Character] = {}
        self._pending: dict[tuple[int, int, int], _Partial] = {}
        self._pending_bytes = 0
        self._completed: set[tuple[int, int, int]] = set()
        self._completed_order: deque[tuple[int, int, int]] = deque()
        self._seen_other: set[int] = set()
        self._seen_unsupported: set[int] = set()
        self._stale_check_ns = -(1 << 62)
        for name in ("packets", "bytes", "samples", "frames", "truncated", "bad_header", "bad_payload", "incomplete",
                     "evicted", "lost", "duplicate", "out_of_order", "counter_resets", "unsupported_type",
                     "other_character", "segment_count_changes"):  # fmt: skip
            self.counters[name] = 0

    # ------------------------------------------------------------------------------ public state
    @property
    def characters(self) -> dict[int, dict[str, Any]]:
        """Per character ID: ``samples``, ``frames``, ``lost``, ``duplicate``, ``out_of_order``,
        ``incomplete``, ``counter_resets``, ``segments`` (of the last pose), ``name`` (from meta
        data, "" until seen), ``last_ns``, ``live`` and ``rate_hz`` (see :meth:`status`)."""
        return {c: st.stats() for c, st in sorted(self._chars.items())}

    def status(self, now_ns: int) -> dict[str, dict[str, Any]]:
        """Per entity ``mvn/<character>``: ``last_ns`` (host time of its last sample), ``live``
        (a sample within ``stale`` seconds of ``now_ns``), ``segments``, ``rate_hz`` (pose
        samples received per second of MVN's clock, over the last 64), ``lost`` and ``name``
        ("" until meta data arrives). Emits ``stale`` events for characters that went silent."""
        self._check_stale(int(now_ns))
        return {st.entity: {"last_ns": st.last_ns, "live": st.live, "segments": st.segments, "rate_hz": st.rate_hz(),
                            "lost": st.lost, "name": st.name}
                for _, st in sorted(self._chars.items())}  # fmt: skip

    # ------------------------------------------------------------------------------ decoding
    def feed(self, packet: RawPacket) -> list:
        counters = self.counters
        data = packet.data
        now = packet.host_time_ns
        counters["packets"] += 1
        counters["bytes"] += len(data)
        if now >= self._stale_check_ns:
            self._stale_check_ns = now + STALE_CHECK_NS
            self._check_stale(now)
        try:
            mtype, counter, dgram, items, tc, char, segs, props, fingers, _ = unpack_header(data)
        except MvnFormatError as e:
            counters["truncated" if e.truncated else "bad_header"] += 1
            return []
        if self.keep is not None and char not in self.keep:
            counters["other_character"] += 1
            if char not in self._seen_other:
                self._seen_other.add(char)
                self.event(now, "other-character", "mvn", f"datagrams of MVN character {char} are ignored "
                           f"(characters={','.join(map(str, sorted(self.keep)))})")  # fmt: skip
            return []
        if mtype not in SUPPORTED:
            counters["unsupported_type"] += 1
            if mtype not in self._seen_unsupported:
                self._seen_unsupported.add(mtype)
                self.event(now, "unsupported-type", "mvn", f"MVN message type {_type_label(mtype)} is not decoded; "
                           "choose quaternion pose (02) in MVN's network streamer")  # fmt: skip
            return []
        key = (char, mtype, counter)
        if key in self._completed:
            self._duplicate(char)
            return []
        if dgram == LAST_PIECE:  # the usual case: the whole message in one datagram
            payload = data[mvn.HEADER_SIZE:]
        else:
            whole = self._add_piece(key, dgram, items, data, (tc, segs, props, fingers))
            if whole is None:
                return []
            payload, items, (tc, segs, props, fingers) = whole
        return self._decode(key, tc, items, segs, props, fingers, payload, now)

    def finish(self) -> list:
        """End of the stream: messages still missing pieces are counted ``incomplete``."""
        for key in list(self._pending):
            self._drop_pending(key, "incomplete")
        return []

    # ------------------------------------------------------------------------------ internals
    def _char(self, cid: int) -> _Character:
        st = self._chars.get(cid)
        if st is None:
            st = self._chars[cid] = _Character(cid)
        return st

    def _duplicate(self, cid: int) -> None:
        self.counters["duplicate"] += 1
        self._char(cid).duplicate += 1

    def _remember(self, key: tuple[int, int, int]) -> None:
        self._completed.add(key)
        self._completed_order.append(key)
        if len(self._completed_order) > COMPLETED_MEMORY:
            self._completed.discard(self._completed_order.popleft())

    def _check_stale(self, now: int) -> None:
        limit = self.stale_ns
        for st in self._chars.values():
            if st.live and now - st.last_ns > limit:
                st.live = False
                self.event(now, "stale", st.entity, f"MVN character {st.id}{' (' + st.name + ')' if st.name else ''} "
                           f"sent nothing for {(now - st.last_ns) / 1e9:.2f} s")  # fmt: skip

    def _drop_pending(self, key, counter_name: str) -> None:
        part = self._pending.pop(key)
        self._pending_bytes -= part.nbytes
        self.counters[counter_name] += 1
        if counter_name == "incomplete":
            self._char(key[0]).incomplete += 1

    def _add_piece(self, key, dgram: int, items: int, data: bytes, head: tuple):
        """Store one piece; the whole message ``(payload, items, head)`` once complete, else None."""
        index, last = dgram & 0x7F, bool(dgram & LAST_PIECE)
        part = self._pending.get(key)
        if part is None:
            while self._pending and (len(self._pending) >= MAX_PENDING
                                     or self._pending_bytes + len(data) > MAX_PENDING_BYTES):  # fmt: skip
                self._drop_pending(next(iter(self._pending)), "evicted")
            part = self._pending[key] = _Partial()
        if index in part.pieces:
            self._duplicate(key[0])
            return None
        if (last and part.last is not None) or (part.last is not None and index > part.last) \
                or (last and part.pieces and max(part.pieces) > index):  # fmt: skip
            self.counters["bad_header"] += 1  # piece indices that contradict each other
            return None
        payload = data[mvn.HEADER_SIZE:]
        part.pieces[index] = (payload, items)
        part.nbytes += len(payload)
        self._pending_bytes += len(payload)
        if index == 0:
            part.head = head
        if last:
            part.last = index
        if part.last is None or len(part.pieces) != part.last + 1:
            return None
        del self._pending[key]
        self._pending_bytes -= part.nbytes
        pieces = part.pieces
        whole = b"".join(pieces[i][0] for i in range(part.last + 1))
        total = sum(pieces[i][1] for i in range(part.last + 1))
        self._expire(key)
        return whole, total, part.head

    def _expire(self, done: tuple[int, int, int]) -> None:
        """Drop pending messages of ``done``'s character and type more than WINDOW counters older."""
        if not self._pending:
            return
        char, mtype, counter = done
        for key in [k for k in self._pending if k[0] == char and k[1] == mtype]:
            if WINDOW < (counter - key[2]) % _U32 < _HALF:
                self._drop_pending(key, "incomplete")

    def _pose_counter(self, st: _Character, u: int, now: int) -> bool:
        """Loss / duplicate / order bookkeeping of pose counter ``u``; False if a duplicate."""
        counters = self.counters
        if st.hi is None:
            st.hi = st.lo = u
        elif u > st.hi:
            gap = u - st.hi - 1
            if gap >= RESET_GAP:
                self._reset(st, u, now, f"jumped ahead by {gap + 1}")
            else:
                st.lost += gap
                counters["lost"] += gap
                st.hi = u
        elif u in st.seen:
            self._duplicate(st.id)
            return False
        elif u < st.hi - SEEN_WINDOW:
            self._reset(st, u, now, f"went back by {st.hi - u}")
        else:  # late: it was counted lost when its gap opened; before the first counter, the gap opens now
            st.out_of_order += 1
            counters["out_of_order"] += 1
            if u > st.lo:
                st.lost -= 1
                counters["lost"] -= 1
            else:
                gap = st.lo - u - 1
                st.lost += gap
                counters["lost"] += gap
                st.lo = u
        seen = st.seen
        seen.add(u)
        if len(seen) > 2 * SEEN_WINDOW:
            floor = st.hi - SEEN_WINDOW
            st.seen = {c for c in seen if c >= floor}
        return True

    def _reset(self, st: _Character, u: int, now: int, how: str) -> None:
        st.counter_resets += 1
        self.counters["counter_resets"] += 1
        self.event(now, "counter-reset", st.entity, f"sample counter of MVN character {st.id} {how}: "
                   "MVN restarted its stream; loss counting starts over")  # fmt: skip
        st.hi = st.lo = u
        st.seen = set()
        st.sc_raw, st.sc_u = u % _U32, u

    def _decode(self, key: tuple[int, int, int], raw_tc: int, items: int, segs: int, props: int, fingers: int,
                payload: bytes, now: int) -> list:  # fmt: skip
        char, mtype, raw_counter = key
        st = self._char(char)
        try:
            if mtype == 2:
                pose = mvn.decode_pose(payload, items, props, fingers)
            elif mtype == 25:
                text, tod_ms = mvn.decode_time_code(payload)
            elif mtype == 12:
                meta = mvn.decode_meta(payload)
            elif mtype == 13:
                scale = mvn.decode_scale(payload)
            elif mtype == 20:
                joints = mvn.decode_joint_angles(payload, items)
            elif mtype == 21:
                lin = mvn.decode_linear_kinematics(payload, items, props, fingers)
            elif mtype == 22:
                ang = mvn.decode_angular_kinematics(payload, items, props, fingers)
            else:  # 24
                com = mvn.decode_center_of_mass(payload, items)
        except MvnFormatError:
            self.counters["bad_payload"] += 1
            return []
        self._remember(key)
        counter = st.unwrap_counter(raw_counter)
        tc = st.unwrap_time(raw_tc)
        head = (char, counter, tc, tc * 1_000_000, now)
        if mtype == 2:
            if not self._pose_counter(st, counter, now):
                return []
            layout = (items, props, fingers)
            if st.layout is not None and layout != st.layout:
                self.counters["segment_count_changes"] += 1
                self.event(now, "segment-count-changed", st.entity,
                           f"MVN character {char} now sends {items} segments ({props} props, {fingers} finger "
                           f"segments), was {st.layout[0]} ({st.layout[1]} props, {st.layout[2]} finger segments)")
            st.layout, st.segments = layout, items
            st.frames += 1
            self.counters["frames"] += 1
            st.rate_tc.append(tc)
            sample = SuitFrame(*head, pose.segment_names, pose.orientations, pose.positions)
        elif mtype == 25:
            sample = SuitTimeCode(*head, text, tod_ms)
        elif mtype == 12:
            st.name = meta.get("name", st.name)
            sample = SuitMeta(*head, meta.get("name", ""), meta.get("xmid", ""), meta.get("color", ""),
                              tuple(meta), tuple(meta.values()))  # fmt: skip
        elif mtype == 13:
            pts = scale.points
            sample = SuitScale(*head, scale.segment_names, scale.segment_origins, tuple(p.name for p in pts),
                               np.array([p.segment_id for p in pts], dtype=np.int64),
                               np.array([p.point_id for p in pts], dtype=np.int64),
                               np.array([p.flags for p in pts], dtype=np.int64),
                               np.array([p.position for p in pts], dtype=np.float64).reshape(-1, 3))  # fmt: skip
        elif mtype == 20:
            sample = JointAngles(*head, *joints)
        elif mtype == 21:
            sample = LinearSegmentKinematics(*head, *lin[1:])
        elif mtype == 22:
            sample = AngularSegmentKinematics(*head, *ang[1:])
        else:
            sample = CenterOfMass(*head, com)
        st.samples += 1
        self.counters["samples"] += 1
        st.last_ns = now
        if not st.live:
            if st.samples > 1:
                self.event(now, "resumed", st.entity, f"MVN character {char} is sending again")
            st.live = True
        return [sample]


def _characters_param(query: dict[str, str], url: str) -> frozenset[int] | None:
    text = query.get("characters", "").strip()
    if not text:
        return None
    out = set()
    for part in text.split(","):
        try:
            c = int(part.strip())
        except ValueError:
            c = -1
        if not 0 <= c <= 255:
            raise SourceError(f"characters={text!r} in {url!r}: {part.strip()!r} is not an MVN character ID",
                              fix="list character IDs 0-255 separated by commas, e.g. characters=0,1")  # fmt: skip
        out.add(c)
    return frozenset(out)


class MvnUdpSource(UdpSource):
    """The MVN network stream on a UDP port (default 9763); see the module docstring for the URL
    and :class:`MvnDecoder` for what comes out."""

    kind = "mvn"
    DEFAULT_PORT = mvn.DEFAULT_PORT
    PARAMS = ("allow", "rcvbuf", "stale", "characters")

    @classmethod
    def make_decoder(cls, url: str) -> MvnDecoder:
        _, query = parse_source_url(url, cls.PARAMS)
        stale = number_param(query, "stale", float, DEFAULT_STALE_S)
        if not (stale > 0 and math.isfinite(stale)):
            raise SourceError(f"stale={query['stale']!r} in {url!r} must be a positive number of seconds",
                              fix="e.g. stale=0.5")  # fmt: skip
        return MvnDecoder(stale_s=stale, characters=_characters_param(query, url))

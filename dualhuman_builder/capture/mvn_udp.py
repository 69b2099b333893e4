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
:meth:`~MvnDecoder.finish`). At most :data:`MAX_PENDING` messages and :data:`MAX_PENDING_BYTES`
bytes of pieces wait, checked at every piece: beyond, the oldest waiting message is dropped
(``evicted``), and a message that alone would exceed the bytes is dropped itself (``evicted``).

Characters: several actors share one port and differ only in the character-ID byte; each is its
own stream (:attr:`SuitFrame.character`) with its own counters in :attr:`MvnDecoder.characters`.
The u32 sample counter and the u32 time code are unwrapped per character (a signed 32-bit step
from the character's newest in-sequence pose; before its first pose, from its first message), so
``sample_counter``, ``time_code_ms`` and ``device_time_ns`` stay monotonic across a wrap. Only
in-sequence poses move that reference: a stray datagram cannot drag it.

Sequence of the type-02 poses of each character. A pose is *in sequence* when it has the
character's layout (segment names, props, finger segments) and its counter lies between
:data:`SEEN_WINDOW` behind and :data:`JUMP_GAP` ahead of the newest, and no more than
:data:`JUMP_GAP` before the oldest. Then:

* ``lost``: counters skipped (a gap) between the oldest and newest seen; a late arrival takes its
  counter back out (loss at the very end of a stream is not seen);
* ``out_of_order``: a counter older than the newest seen that had not arrived yet (yielded);
* ``duplicate``: a datagram received before (a piece of a message still waiting, or any datagram
  of a message decoded among the last :data:`COMPLETED_MEMORY`), or a pose whose counter was
  already yielded; never yielded twice.

A pose that is not in sequence (a far jump of the counter, another layout) is held back, not
yielded and not counted as loss. Held poses that follow each other (same layout, counters within
:data:`JUMP_GAP`) form a candidate stream (at most :data:`MAX_CANDIDATES` per character, the one
heard from longest ago is dropped first). A candidate that reaches :data:`CONFIRM` poses before the
character's stream moves forward again is the stream now: its poses are yielded, in arrival order,
and it becomes the reference —

* another layout (a prop added, finger tracking switched on): ``segment_count_changes``, event
  ``segment-count-changed``; the counter goes on as before;
* a forward jump the time code accounts for (at most :data:`MAX_RATE_HZ` counters per second of
  time code, and under :data:`RESET_GAP`): an outage, its counters are ``lost``;
* any other jump: MVN restarted its counter (``counter_resets``, event ``counter-reset``), not loss.

Held poses whose candidate is dropped (the character's stream went on, a newer candidate took the
place, or the stream ended: :meth:`MvnDecoder.finish`) are counted ``out_of_sequence``: a stray
datagram (another sender using the character ID, a corrupted counter) adds at most
:data:`JUMP_GAP` to ``lost`` and never moves the stream, and a lone pose of another segment count
never flips the layout. Poses are therefore yielded with one layout per character between
``segment-count-changed`` events. Other message types are yielded as they come.

Liveness: a character is live from its first sample until it has sent nothing for ``stale``
seconds of host time; going stale emits ``stale`` (noticed by the next datagram of any character,
checked at most every :data:`STALE_CHECK_NS`, or by :meth:`MvnDecoder.status`), its next sample
``resumed``. A change of a character's pose layout (number of segments, props or finger segments:
MVN recomposed the scene) emits ``segment-count-changed`` once confirmed (above). The
``counter-reset`` and ``segment-count-changed`` events of a character come at most once per
:data:`EVENT_INTERVAL_NS` of host time; those in between are counted only, and the next event
says how many.

MVN datagrams carry no checksum: corruption is caught only where it breaks the layout (ID string,
sizes, item counts, strings, non-finite values, quaternion norms); a flipped bit in a position or
in a counter goes through as a wrong value.

Counters (:attr:`Decoder.counters`): ``packets``, ``bytes``, ``samples`` (all types), ``frames``
(type 02), ``truncated`` (shorter than the header or than its payload-size field says),
``bad_header`` (ID string, payload size shorter than the datagram, inconsistent piece indices),
``bad_payload`` (a complete message that does not decode), ``incomplete``, ``evicted``, ``lost``,
``duplicate``, ``out_of_order``, ``out_of_sequence``, ``counter_resets``, ``unsupported_type``,
``other_character`` (datagrams of characters not in ``characters=``), ``segment_count_changes``.
Memory is bounded: pieces as above, :data:`COMPLETED_MEMORY` message keys, per character
2 x :data:`SEEN_WINDOW` counters and :data:`MAX_CANDIDATES` x :data:`CONFIRM` held poses. Events: ``stale``,
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
from dualhuman_builder.capture.sources import (Decoder, RawPacket, SourceError, number_param, parse_source_url,
                                               rate_limited)  # fmt: skip
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
#: Pose sample counters remembered per character to tell duplicates from late arrivals; a counter
#: further behind the newest is out of sequence.
SEEN_WINDOW = 1024
#: Largest forward step of a character's pose counter taken at once (a quarter second at 240 Hz);
#: a larger one is out of sequence until confirmed.
JUMP_GAP = 64
#: Held poses that confirm a candidate stream, and most candidate streams held per character.
CONFIRM = 4
MAX_CANDIDATES = 4
#: A confirmed forward jump counts as loss when MVN's time code advanced enough for it at this many
#: counters per second (MVN streams at most 240 Hz) and it is smaller than :data:`RESET_GAP`.
MAX_RATE_HZ = 1000
#: A confirmed jump of the sample counter this large or larger is a restart of MVN's counter, not
#: loss (2^20 samples: over an hour at 240 Hz).
RESET_GAP = 1 << 20
#: Host ns between two ``counter-reset`` (or two ``segment-count-changed``) events of a character.
EVENT_INTERVAL_NS = 1_000_000_000
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

    __slots__ = ("id", "entity", "samples", "frames", "lost", "duplicate", "out_of_order", "out_of_sequence",
                 "incomplete", "counter_resets", "segments", "layout", "key", "name", "last_ns", "live", "hi", "lo",
                 "seen", "c0", "tc_ref", "rate_tc", "held", "arrivals", "quiet")  # fmt: skip

    def __init__(self, cid: int):
        self.id = cid
        self.entity = f"mvn/{cid}"
        self.samples = self.frames = self.lost = self.duplicate = self.out_of_order = self.out_of_sequence = 0
        self.incomplete = self.counter_resets = 0
        self.segments = 0  # segments of the stream's poses
        self.layout: tuple[int, int, int] | None = None  # (items, props, fingers) of the stream's poses
        self.key: tuple | None = None  # (segment names, props, fingers): what "the same layout" compares
        self.name = ""
        self.last_ns: int | None = None
        self.live = False
        self.hi: int | None = None  # newest in-sequence unwrapped pose counter (the unwrapping reference)
        self.lo = 0  # oldest pose counter since the stream (re)started
        self.seen: set[int] = set()
        self.c0: int | None = None  # the first counter, the reference until a pose arrives
        self.tc_ref: int | None = None  # unwrapped time code of the newest in-sequence pose (or the first message)
        self.rate_tc: deque[int] = deque(maxlen=RATE_WINDOW)
        self.held: list[_Held] = []  # candidate streams of out-of-sequence poses
        self.arrivals = 0  # out-of-sequence poses so far (orders the candidates by when last heard)
        self.quiet: dict[str, tuple[int, int]] = {}  # event kind -> (host ns of the last emitted, suppressed since)

    def unwrap_counter(self, raw: int) -> int:
        ref = self.hi if self.hi is not None else self.c0
        if ref is None:
            self.c0 = raw
            return raw
        return ref + ((raw - ref + _HALF) % _U32) - _HALF

    def unwrap_time(self, raw: int) -> int:
        ref = self.tc_ref
        if ref is None:
            self.tc_ref = raw
            return raw
        return ref + ((raw - ref + _HALF) % _U32) - _HALF

    def rate_hz(self) -> float:
        tc = self.rate_tc
        if len(tc) < 2:
            return 0.0
        span = max(tc) - min(tc)
        return (len(tc) - 1) * 1000.0 / span if span > 0 else 0.0

    def stats(self) -> dict[str, Any]:
        return {"samples": self.samples, "frames": self.frames, "lost": self.lost, "duplicate": self.duplicate,
                "out_of_order": self.out_of_order, "out_of_sequence": self.out_of_sequence,
                "incomplete": self.incomplete,
                "counter_resets": self.counter_resets, "segments": self.segments, "name": self.name,
                "last_ns": self.last_ns, "live": self.live, "rate_hz": self.rate_hz()}  # fmt: skip


class _Held:
    """One candidate stream: out-of-sequence poses of one layout whose counters follow each other,
    as ``(counter, time code, sample)`` in arrival order."""

    __slots__ = ("key", "layout", "items", "counters", "lo", "hi", "last")

    def __init__(self, key: tuple, layout: tuple[int, int, int]):
        self.key, self.layout = key, layout
        self.items: list[tuple[int, int, SuitFrame]] = []
        self.counters: set[int] = set()
        self.lo = self.hi = self.last = 0

    def follows(self, key: tuple, u: int) -> bool:
        return key == self.key and self.lo - JUMP_GAP <= u <= self.hi + JUMP_GAP

    def add(self, u: int, tc: int, sample: SuitFrame, arrival: int) -> None:
        if not self.items:
            self.lo = self.hi = u
        self.items.append((u, tc, sample))
        self.counters.add(u)
        self.lo, self.hi, self.last = min(self.lo, u), max(self.hi, u), arrival


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
                     "evicted", "lost", "duplicate", "out_of_order", "out_of_sequence", "counter_resets",
                     "unsupported_type", "other_character", "segment_count_changes"):  # fmt: skip
            self.counters[name] = 0

    # ------------------------------------------------------------------------------ public state
    @property
    def characters(self) -> dict[int, dict[str, Any]]:
        """Per character ID: ``samples``, ``frames``, ``lost``, ``duplicate``, ``out_of_order``,
        ``out_of_sequence``, ``incomplete``, ``counter_resets``, ``segments`` (of the last pose), ``name`` (from meta
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
        """End of the stream: messages still missing pieces are counted ``incomplete``, poses still
        held out of sequence ``out_of_sequence``."""
        for key in list(self._pending):
            self._drop_pending(key, "incomplete")
        for st in self._chars.values():
            self._drop_held(st)
        return []

    def recover(self) -> None:
        """After a fault the decoder did not foresee: drop the messages waiting for pieces
        (``evicted``) and the held poses (``out_of_sequence``); counters and streams stay."""
        for key in list(self._pending):
            self._drop_pending(key, "evicted")
        for st in self._chars.values():
            self._drop_held(st)

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
            while len(self._pending) >= MAX_PENDING:
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
        while self._pending_bytes + len(payload) > MAX_PENDING_BYTES:  # every piece, not only a new message's
            oldest = next((k for k in self._pending if k != key), None)
            self._drop_pending(key if oldest is None else oldest, "evicted")
            if oldest is None:  # this message alone would exceed the bound
                return None
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

    def _pose(self, st: _Character, u: int, tc: int, sample: SuitFrame, key: tuple, layout: tuple[int, int, int],
              now: int) -> list:  # fmt: skip
        """Route one decoded pose: in sequence (yielded) or held as a candidate (module docstring)."""
        hi = st.hi
        if hi is None:
            st.key, st.layout, st.segments = key, layout, layout[0]
        elif key != st.key or not max(hi - SEEN_WINDOW, st.lo - JUMP_GAP) <= u <= hi + JUMP_GAP:
            return self._hold_pose(st, u, tc, sample, key, layout, now)
        elif u > hi and st.held:  # the stream went on: what was held was not it
            self._drop_held(st)
        return self._frame(st, u, tc, sample, now)

    def _frame(self, st: _Character, u: int, tc: int, sample: SuitFrame, now: int) -> list:
        if not self._pose_counter(st, u, tc):
            return []
        self._remember((st.id, 2, u % _U32))  # a held pose is not: a stray must not shadow the real one
        st.frames += 1
        self.counters["frames"] += 1
        st.rate_tc.append(tc)
        return self._yield(st, sample, now)

    def _pose_counter(self, st: _Character, u: int, tc: int) -> bool:
        """Loss / duplicate / order bookkeeping of an in-sequence pose counter ``u`` (time code
        ``tc``); False if a duplicate."""
        counters = self.counters
        if st.hi is None:
            st.hi = st.lo = u
            st.tc_ref = tc
        elif u > st.hi:
            gap = u - st.hi - 1
            st.lost += gap
            counters["lost"] += gap
            st.hi, st.tc_ref = u, tc
        elif u in st.seen:
            self._duplicate(st.id)
            return False
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

    def _hold_pose(self, st: _Character, u: int, tc: int, sample: SuitFrame, key: tuple,
                   layout: tuple[int, int, int], now: int) -> list:
        """Keep an out-of-sequence pose with the candidate it follows; confirm that candidate once
        it holds CONFIRM poses."""
        st.arrivals += 1
        cand = next((h for h in st.held if h.follows(key, u)), None)
        if cand is None:
            if len(st.held) >= MAX_CANDIDATES:
                gone = min(st.held, key=lambda h: h.last)
                st.held.remove(gone)
                self._out_of_sequence(st, len(gone.items))
            cand = _Held(key, layout)
            st.held.append(cand)
        elif u in cand.counters:
            self._duplicate(st.id)
            return []
        cand.add(u, tc, sample, st.arrivals)
        if len(cand.items) < CONFIRM:
            return []
        st.held.remove(cand)
        self._drop_held(st)
        return self._confirm(st, cand, now)

    def _confirm(self, st: _Character, cand: _Held, now: int) -> list:
        """The candidate is the character's stream now: classify the jump, then yield its poses."""
        lo, lo_tc = min((u, tc) for u, tc, _ in cand.items)
        hi = st.hi
        gap = lo - hi - 1
        outage = 0 <= gap < RESET_GAP and gap <= JUMP_GAP + max(0, lo_tc - st.tc_ref) * MAX_RATE_HZ // 1000
        if not (hi - SEEN_WINDOW <= lo <= hi + JUMP_GAP or outage):
            how = f"jumped ahead by {lo - hi}" if lo > hi else f"went back by {hi - lo}"
            st.counter_resets += 1
            self.counters["counter_resets"] += 1
            self._event_limited(now, "counter-reset", st, f"sample counter of MVN character {st.id} {how}: MVN "
                                "restarted its stream (or another sender uses this character ID); loss counting "
                                "starts over")  # fmt: skip
            st.hi, st.seen = None, set()
            st.rate_tc.clear()
        if cand.key != st.key:
            items, props, fingers = cand.layout
            self.counters["segment_count_changes"] += 1
            self._event_limited(now, "segment-count-changed", st,
                                f"MVN character {st.id} now sends {items} segments ({props} props, {fingers} finger "
                                f"segments), was {st.layout[0]} ({st.layout[1]} props, {st.layout[2]} finger "
                                "segments)")  # fmt: skip
            st.key, st.layout, st.segments = cand.key, cand.layout, cand.layout[0]
        out: list = []
        for u, tc, sample in cand.items:
            out += self._frame(st, u, tc, sample, now)
        return out

    def _out_of_sequence(self, st: _Character, n: int) -> None:
        st.out_of_sequence += n
        self.counters["out_of_sequence"] += n

    def _drop_held(self, st: _Character) -> None:
        for h in st.held:
            self._out_of_sequence(st, len(h.items))
        st.held = []

    def _event_limited(self, now: int, kind: str, st: _Character, message: str) -> None:
        """An event of ``kind`` for character ``st``, at most one per EVENT_INTERVAL_NS of host time."""
        message = rate_limited(st.quiet, kind, now, EVENT_INTERVAL_NS, message)
        if message is not None:
            self.event(now, kind, st.entity, message)

    def _yield(self, st: _Character, sample, now: int) -> list:
        st.samples += 1
        self.counters["samples"] += 1
        st.last_ns = now
        if not st.live:
            if st.samples > 1:
                self.event(now, "resumed", st.entity, f"MVN character {st.id} is sending again")
            st.live = True
        return [sample]

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
        if mtype != 2:
            self._remember(key)
        counter = st.unwrap_counter(raw_counter)
        tc = st.unwrap_time(raw_tc)
        head = (char, counter, tc, tc * 1_000_000, now)
        if mtype == 2:
            sample = SuitFrame(*head, pose.segment_names, pose.orientations, pose.positions)
            return self._pose(st, counter, tc, sample, (pose.segment_names, props, fingers), (items, props, fingers),
                              now)  # fmt: skip
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
        return self._yield(st, sample, now)


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

"""Xsens MVN real-time network stream ("MXTP") datagrams: encoders for types 02, 12, 13 and 25;
header and payload decoders for types 02, 12, 13, 20, 21, 22, 24 and 25 (see "Decoding" below).

Layout (Xsens, "MVN real-time network streaming protocol specification", "the spec" below;
parsers in ``hrii-iit/xsens_mvn_sdk`` and ``xsens/xsens_mvn_ros2``; all fields **big-endian**):
every datagram is a 24-byte :data:`HEADER` ``'>6sIBBIBBBBHH'`` — ID string ``b"MXTP" + two ASCII
digits`` of the message type, sample counter (u32), datagram counter (u8), number of items in
this datagram (u8), time code (u32, ms since the start of the recording clock), character ID
(u8), number of body segments (u8), props (u8), finger segments (u8), reserved (u16, zero),
payload size (u16, bytes after the header) — followed by the payload.

Several characters (actors) on one port differ **only** in the character-ID byte (offset 16).

Splitting: a message longer than ``max_datagram`` bytes (header included; default
:data:`DEFAULT_MAX_DATAGRAM`, an Ethernet MTU) goes out as several datagrams with the same sample
counter, each with its own header. The datagram counter's low 7 bits are the piece's index, its
top bit is set on the last piece (one piece: 0x80; three: 0x00, 0x01, 0x82); a receiver
concatenates the payloads in index order. Pose messages (type 02) split at item boundaries and
each piece's item count is the number of segments in it. Other messages split at byte boundaries;
their first piece carries the message's item count and later pieces 0. Either way the item counts
of the pieces sum to the message's.

Conflicts in the sources, and the readings chosen here:

* **Position unit of type 02 (and 13): metres.** The spec (section 2.5.6) says positions are in
  cm, but Xsens' own SDK (``hrii-iit/xsens_mvn_sdk``) scales only type-01 positions by 1/100,
  i.e. type 02 arrives in metres, and that is what MVN sends in practice.
* **Type 25 payload: int32 length + ``HH:MM:SS.mmm``** (16 bytes). The spec's type-25 section
  says "12 byte string", but its rule for strings (2.5.12: int32-length-prefixed UTF-8, no
  terminator) gives the prefixed form. Hours wrap at 24.
* **Point IDs** (100*seg+pt vs 256*seg+pt) do not arise: type 13 sends the segment ID and the
  point's local ID as two separate u16 fields. Type 23 (item size 44 vs 68) is not encoded.

Frames: samples are Y-up (:mod:`dualhuman_builder.conventions`); types 02 and 13 are MVN's
**Z-up**, right-handed frame. Positions go through the inverse of ``ZUP_TO_YUP``
(``(x, y, z) -> (x, -z, y)``) and orientations are left-multiplied by it
(:func:`~dualhuman_builder.capture.wire.to_zup_wxyz`), quaternions sent as ``(re, i, j, k)``.
A body facing our +X stands in MVN's null pose (all segment orientations identity).

Decoding (:func:`parse_header`, ``decode_*``) inverts the encoders exactly and reads the types
MVN sends that we do not encode; malformed input raises :class:`MvnFormatError`. Readings chosen
for the types without an encoder (the spec states no units for them):

* **20 joint angles**: parent and child *point IDs* (``256 * segment ID + local point ID``, spec
  2.5.10) and three rotations about the segment axes, sent in **degrees** (as MVN shows and exports
  joint angles), returned in radians. A segment's own axes do not change with the world frame.
* **21 / 22**: positions m, velocities m/s, accelerations m/s^2, angular velocities rad/s and
  accelerations rad/s^2 (MVN's SI units, as in MVNX), world vectors in MVN's Z-up frame, converted
  to Y-up like type 02.
* **24 centre of mass**: one 12-byte item, metres, Z-up -> Y-up.
* **Segment IDs** (:func:`segment_name`): body 1..23 (:data:`MVN_SEGMENTS`); with finger tracking
  (header fingers > 0) props are ``24 .. 23 + props`` and the 40 finger segments
  (:data:`FINGER_SEGMENTS`, left hand then right) follow them (spec table 2: left carpus index
  ``23 + props``); without fingers IDs 24..27 are Prop1..Prop4 whatever the prop count (the
  encoder's numbering). Any other ID is named ``Segment<ID>``.
"""

from __future__ import annotations

import functools
import math
import re
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Iterable, Mapping, NamedTuple, Sequence

import numpy as np

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.samples import SuitFrame
from dualhuman_builder.capture.wire import check_finite, check_unit_quaternions, to_zup_wxyz
from dualhuman_builder.conventions import ZUP_TO_YUP, yup_to_zup_points

#: Default UDP port of the MVN network stream.
DEFAULT_PORT = 9763
#: The datagram header: id string, sample counter, datagram counter, items, time code (ms),
#: character ID, body segments, props, finger segments, reserved, payload size.
HEADER = struct.Struct(">6sIBBIBBBBHH")
HEADER_SIZE = HEADER.size  # 24
#: One type-02 item: segment ID (i32), position x, y, z (f32, metres, Z-up), quaternion re, i, j, k.
POSE_QUATERNION_ITEM = struct.Struct(">i7f")
#: Datagram counter bit set on the last piece of a message.
LAST_PIECE = 0x80
#: Largest datagram (header included) the encoders write unless told otherwise: an Ethernet MTU.
DEFAULT_MAX_DATAGRAM = 1500
#: Segment IDs of props (Prop1..Prop4); body segments are 1..23 (index in MVN_SEGMENTS + 1).
PROP_SEGMENTS = ("Prop1", "Prop2", "Prop3", "Prop4")
#: Body segments of a suit, as MVN reports in every header (even of non-pose messages).
BODY_SEGMENT_COUNT = len(MVN_SEGMENTS)


class MvnMessageType(IntEnum):
    """Message types; on the wire as two ASCII digits after ``MXTP`` (see :func:`id_string`)."""

    POSE_EULER = 1
    POSE_QUATERNION = 2
    POINTS = 3
    TAG_DEPRECATED = 4
    POSE_UNITY = 5
    SCALE_DEPRECATED = 10
    PROP_DEPRECATED = 11
    META = 12
    SCALE = 13
    JOINT_ANGLES = 20
    LINEAR_KINEMATICS = 21
    ANGULAR_KINEMATICS = 22
    TRACKER_KINEMATICS = 23
    CENTER_OF_MASS = 24
    TIME_CODE = 25


#: Bytes per item of the fixed-size message types (02 and those a receiver may meet).
ITEM_SIZES = {
    MvnMessageType.POSE_EULER: 28,
    MvnMessageType.POSE_QUATERNION: 32,
    MvnMessageType.POINTS: 16,
    MvnMessageType.POSE_UNITY: 32,
    MvnMessageType.JOINT_ANGLES: 20,
    MvnMessageType.LINEAR_KINEMATICS: 40,
    MvnMessageType.ANGULAR_KINEMATICS: 44,
    MvnMessageType.CENTER_OF_MASS: 12,
}


def id_string(message_type: int) -> bytes:
    """The 6-byte ID string of a message type: ``id_string(2) == b"MXTP02"``."""
    if not 0 <= int(message_type) <= 99:
        raise ValueError(f"MVN message type must be 0..99, got {message_type}")
    return b"MXTP%02d" % int(message_type)


def segment_id(name: str) -> int:
    """MVN segment ID of a body segment (1..23, index in ``MVN_SEGMENTS`` + 1) or prop (24..27)."""
    if name in MVN_SEGMENTS:
        return MVN_SEGMENTS.index(name) + 1
    if name in PROP_SEGMENTS:
        return BODY_SEGMENT_COUNT + 1 + PROP_SEGMENTS.index(name)
    raise ValueError(f"unknown MVN segment {name!r}; body segments are {list(MVN_SEGMENTS)}, "
                     f"props {list(PROP_SEGMENTS)}")


def _u8(value: int, what: str) -> int:
    if not 0 <= int(value) <= 0xFF:
        raise ValueError(f"{what} must fit in one byte (0..255), got {value}")
    return int(value)


def encode_datagrams(
    message_type: int,
    payload: bytes,
    *,
    items: int,
    character: int = 0,
    sample_counter: int = 0,
    time_code_ms: int = 0,
    segments: int = BODY_SEGMENT_COUNT,
    props: int = 0,
    fingers: int = 0,
    item_size: int | None = None,
    max_datagram: int = DEFAULT_MAX_DATAGRAM,
) -> list[bytes]:
    """One message as datagrams: header(s) + payload, split when longer than ``max_datagram``.

    ``item_size`` given: the payload is ``items`` fixed-size items and pieces split between
    items; otherwise pieces split anywhere and the first carries ``items`` (see the module
    docstring). ``sample_counter`` and ``time_code_ms`` wrap to u32. At most 128 pieces.
    """
    if max_datagram <= HEADER_SIZE:
        raise ValueError(f"max_datagram must exceed the {HEADER_SIZE}-byte header, got {max_datagram}")
    if time_code_ms < 0 or sample_counter < 0:
        raise ValueError("sample counter and time code must not be negative")
    room = max_datagram - HEADER_SIZE
    if item_size is not None:
        if len(payload) != items * item_size:
            raise ValueError(f"payload of {len(payload)} bytes is not {items} items of {item_size} bytes")
        per_piece = room // item_size
        if per_piece < 1:
            raise ValueError(f"max_datagram {max_datagram} cannot hold one {item_size}-byte item")
        per_piece = min(per_piece, 0xFF)
        bounds = [(i * item_size, min(items, i + per_piece) * item_size, min(per_piece, items - i))
                  for i in range(0, max(items, 1), per_piece)]
    else:
        bounds = [(i, min(len(payload), i + room), items if i == 0 else 0)
                  for i in range(0, max(len(payload), 1), room)]
    if len(bounds) > 0x80:
        raise ValueError(f"message of {len(payload)} bytes needs {len(bounds)} datagrams; "
                         f"the 7-bit datagram index allows 128 (raise max_datagram)")
    head = (id_string(message_type), sample_counter & 0xFFFFFFFF)
    tail = (time_code_ms & 0xFFFFFFFF, _u8(character, "character ID"), _u8(segments, "segment count"),
            _u8(props, "prop count"), _u8(fingers, "finger segment count"), 0)
    out = []
    for k, (a, b, n) in enumerate(bounds):
        counter = k | (LAST_PIECE if k == len(bounds) - 1 else 0)
        piece = payload[a:b]
        out.append(HEADER.pack(*head, counter, _u8(n, "item count"), *tail, len(piece)) + piece)
    return out


# ----------------------------------------------------------------------------------- type 02
def encode_pose(frame: SuitFrame, *, max_datagram: int = DEFAULT_MAX_DATAGRAM) -> list[bytes]:
    """A :class:`SuitFrame` as type-02 datagrams (one for 23 segments at the default size).

    Items in segment-ID order (body, then props), each ``'>i7f'``: segment ID, position in metres
    and orientation ``(re, i, j, k)``, both in MVN's Z-up frame. Header: the frame's character,
    sample counter and time code; segment and prop counts of the frame; no finger segments.
    Raises ``ValueError`` on unknown segment names, non-finite positions or non-unit quaternions.
    """
    names = tuple(frame.segment_names)
    ids = [segment_id(n) for n in names]
    if len(set(ids)) != len(ids):
        raise ValueError(f"segment names repeat in frame: {names}")
    pos = check_finite(frame.positions, f"positions of character {frame.character}")
    quat = np.asarray(frame.orientations, dtype=np.float64)
    if pos.shape != (len(names), 3) or quat.shape != (len(names), 4):
        raise ValueError(f"positions {pos.shape} / orientations {quat.shape} do not match {len(names)} segments")
    check_unit_quaternions(quat, f"orientation of character {frame.character}")
    pos_z = yup_to_zup_points(pos)
    quat_z = to_zup_wxyz(quat)
    order = np.argsort(ids, kind="stable")
    payload = b"".join(POSE_QUATERNION_ITEM.pack(ids[i], *pos_z[i], *quat_z[i]) for i in order)
    n_props = sum(i > BODY_SEGMENT_COUNT for i in ids)
    return encode_datagrams(
        MvnMessageType.POSE_QUATERNION, payload, items=len(ids), item_size=POSE_QUATERNION_ITEM.size,
        character=frame.character, sample_counter=frame.sample_counter, time_code_ms=frame.time_code_ms,
        segments=len(ids) - n_props, props=n_props, fingers=0, max_datagram=max_datagram,
    )


# ----------------------------------------------------------------------------------- strings
def mvn_string(text: str) -> bytes:
    """An MVN string: int32 byte length (big-endian) + UTF-8 bytes, no terminator."""
    raw = text.encode("utf-8")
    return struct.pack(">i", len(raw)) + raw


_TAG = re.compile(r"^[^:\n]+$")


def encode_meta(
    character: int,
    *,
    name: str,
    xmid: str = "",
    color: str = "",
    extra: Mapping[str, str] | None = None,
    sample_counter: int = 0,
    time_code_ms: int = 0,
    segments: int = BODY_SEGMENT_COUNT,
    props: int = 0,
    fingers: int = 0,
    max_datagram: int = DEFAULT_MAX_DATAGRAM,
) -> list[bytes]:
    """Type-12 meta data: one MVN string of ``tag:value\\n`` lines, tags ``name``, ``xmid`` (the
    BodyPack/Awinda station ID), ``color`` (hex ``RRGGBB``) and any ``extra`` tags, in that order;
    empty values are left out. One item."""
    if color and not re.fullmatch(r"[0-9A-Fa-f]{6}", color):
        raise ValueError(f"color must be hex RRGGBB, got {color!r}")
    tags = {"name": name, "xmid": xmid, "color": color.upper(), **(extra or {})}
    lines = []
    for tag, value in tags.items():
        if not _TAG.match(tag):
            raise ValueError(f"meta tag {tag!r} must be non-empty without ':' or newline")
        if "\n" in str(value):
            raise ValueError(f"meta value of {tag!r} must not contain a newline")
        if value != "":
            lines.append(f"{tag}:{value}\n")
    return encode_datagrams(
        MvnMessageType.META, mvn_string("".join(lines)), items=1, character=character,
        sample_counter=sample_counter, time_code_ms=time_code_ms, segments=segments, props=props,
        fingers=fingers, max_datagram=max_datagram,
    )


# ----------------------------------------------------------------------------------- type 13
@dataclass(frozen=True)
class ScalePoint:
    """A named point of the null pose: ``segment_id`` (1..27), ``point_id`` (local, u16),
    ``flags`` (u32) and ``position (3,)`` relative to the segment origin, Y-up world metres."""

    segment_id: int
    point_id: int
    name: str
    flags: int
    position: Sequence[float]


_SCALE_COUNT = struct.Struct(">i")
_SCALE_VEC = struct.Struct(">3f")
_SCALE_POINT_IDS = struct.Struct(">HH")
_SCALE_FLAGS = struct.Struct(">I")


def _scale_point(p: ScalePoint) -> bytes:
    if not (0 <= p.segment_id <= 0xFFFF and 0 <= p.point_id <= 0xFFFF and 0 <= p.flags <= 0xFFFFFFFF):
        raise ValueError(f"scale point {p.name!r}: segment/point IDs must be u16 and flags u32")
    v = yup_to_zup_points(check_finite(p.position, f"scale point {p.name!r}"))
    return (_SCALE_POINT_IDS.pack(p.segment_id, p.point_id) + mvn_string(p.name)
            + _SCALE_FLAGS.pack(p.flags) + _SCALE_VEC.pack(*v))


def encode_scale(
    character: int,
    segment_origins: Mapping[str, Sequence[float]] | Iterable[tuple[str, Sequence[float]]],
    points: Sequence[ScalePoint] = (),
    *,
    sample_counter: int = 0,
    time_code_ms: int = 0,
    segments: int = BODY_SEGMENT_COUNT,
    props: int = 0,
    fingers: int = 0,
    max_datagram: int = DEFAULT_MAX_DATAGRAM,
) -> list[bytes]:
    """Type-13 scale information of the null pose, as MVN sends it: several messages.

    Payload of each message: ``i32 S``, S x (segment name as an MVN string, origin ``3 x f32``),
    ``i32 P``, P x (``u16`` segment ID, ``u16`` point ID, name string, ``u32`` flags, position
    relative to the segment origin ``3 x f32``); metres, MVN's Z-up frame (origins given in our
    Y-up world, of the actor in the null pose: facing +X). The first message holds the segments
    and P = 0; then messages with S = 0 and as many points as fit in one datagram. The messages
    get consecutive sample counters from ``sample_counter`` on, so that (sample counter,
    datagram counter) stays unique per datagram; a segment list longer than one datagram is split
    with the datagram counter. Item count = S + P of the message.
    """
    pairs = list(segment_origins.items()) if isinstance(segment_origins, Mapping) else list(segment_origins)
    body = b"".join(mvn_string(name) + _SCALE_VEC.pack(*yup_to_zup_points(check_finite(o, f"origin of {name!r}")))
                    for name, o in pairs)
    messages = [(_SCALE_COUNT.pack(len(pairs)) + body + _SCALE_COUNT.pack(0), len(pairs))]
    room = max_datagram - HEADER_SIZE - 2 * _SCALE_COUNT.size
    chunk: list[bytes] = []
    for raw in map(_scale_point, points):
        if chunk and sum(map(len, chunk)) + len(raw) > room:
            messages.append((_SCALE_COUNT.pack(0) + _SCALE_COUNT.pack(len(chunk)) + b"".join(chunk), len(chunk)))
            chunk = []
        chunk.append(raw)
    if chunk:
        messages.append((_SCALE_COUNT.pack(0) + _SCALE_COUNT.pack(len(chunk)) + b"".join(chunk), len(chunk)))
    out = []
    for k, (payload, items) in enumerate(messages):
        out += encode_datagrams(
            MvnMessageType.SCALE, payload, items=min(items, 0xFF), character=character,
            sample_counter=sample_counter + k, time_code_ms=time_code_ms, segments=segments, props=props,
            fingers=fingers, max_datagram=max_datagram,
        )
    return out


# ----------------------------------------------------------------------------------- type 25
def time_code_text(time_code_ms: int) -> str:
    """``HH:MM:SS.mmm`` of a time in ms (hours wrap at 24)."""
    if time_code_ms < 0:
        raise ValueError(f"time code must not be negative, got {time_code_ms}")
    s, ms = divmod(int(time_code_ms), 1000)
    m, s = divmod(s, 60)
    h, m = divmod(m, 60)
    return f"{h % 24:02d}:{m:02d}:{s:02d}.{ms:03d}"


def encode_time_code(
    time_code_ms: int,
    *,
    character: int = 0,
    sample_counter: int = 0,
    segments: int = BODY_SEGMENT_COUNT,
    props: int = 0,
    fingers: int = 0,
    max_datagram: int = DEFAULT_MAX_DATAGRAM,
) -> list[bytes]:
    """Type-25 time code: payload int32 length 12 + ASCII ``HH:MM:SS.mmm``; header time code is
    the same instant in ms. Sent with the pose of the same sample (same sample counter). One item."""
    return encode_datagrams(
        MvnMessageType.TIME_CODE, mvn_string(time_code_text(time_code_ms)), items=1, character=character,
        sample_counter=sample_counter, time_code_ms=time_code_ms, segments=segments, props=props,
        fingers=fingers, max_datagram=max_datagram,
    )


def encode_frame(frame: SuitFrame, *, time_code: bool = True, max_datagram: int = DEFAULT_MAX_DATAGRAM) -> list[bytes]:
    """Everything MVN sends for one sample of one character: the type-02 pose datagrams, then
    (``time_code``) the type-25 time code with the same sample counter."""
    out = encode_pose(frame, max_datagram=max_datagram)
    if time_code:
        n_props = sum(n in PROP_SEGMENTS for n in frame.segment_names)
        out += encode_time_code(frame.time_code_ms, character=frame.character, sample_counter=frame.sample_counter,
                                segments=len(frame.segment_names) - n_props, props=n_props,
                                max_datagram=max_datagram)
    return out


# =================================================================================== decoding
class MvnFormatError(ValueError):
    """A datagram or payload that does not follow the MXTP layout. ``truncated`` is True when
    bytes are missing (shorter than the header, or fewer payload bytes than its size field says)."""

    def __init__(self, message: str, *, truncated: bool = False):
        super().__init__(message)
        self.truncated = truncated


@dataclass(frozen=True, slots=True)
class MvnHeader:
    """A parsed datagram header (see the module docstring). ``datagram_index``: low 7 bits of
    the datagram counter; ``last_piece``: its top bit; ``time_code_ms``: u32 ms as sent (not
    unwrapped); ``payload_size``: bytes after the header (checked against the datagram)."""

    message_type: int
    sample_counter: int
    datagram_index: int
    last_piece: bool
    items: int
    time_code_ms: int
    character: int
    segments: int
    props: int
    fingers: int
    payload_size: int


def unpack_header(data: bytes) -> tuple[int, int, int, int, int, int, int, int, int, int]:
    """The fast form of :func:`parse_header`: ``(message type, sample counter, datagram counter
    byte, items, time code ms, character, body segments, props, fingers, payload size)``.
    Raises :class:`MvnFormatError` as :func:`parse_header` does."""
    n = len(data)
    if n < HEADER_SIZE:
        raise MvnFormatError(f"datagram of {n} bytes is shorter than the {HEADER_SIZE}-byte MXTP header",
                             truncated=True)  # fmt: skip
    ident, counter, dgram, items, tc, char, segs, props, fingers, _, size = HEADER.unpack_from(data)
    d0, d1 = ident[4], ident[5]
    if ident[:4] != b"MXTP" or not (48 <= d0 <= 57 and 48 <= d1 <= 57):
        raise MvnFormatError(f"bad ID string {ident!r}: expected b'MXTP' and two ASCII digits")
    if size != n - HEADER_SIZE:
        raise MvnFormatError(f"payload size field says {size} bytes but {n - HEADER_SIZE} follow the header",
                             truncated=size > n - HEADER_SIZE)  # fmt: skip
    return (d0 - 48) * 10 + d1 - 48, counter, dgram, items, tc, char, segs, props, fingers, size


def parse_header(data: bytes) -> MvnHeader:
    """The 24-byte header of one datagram. Raises :class:`MvnFormatError` when the datagram is
    shorter than the header, its ID string is not ``MXTP`` + two digits, or its payload-size field
    disagrees with the bytes after the header (``truncated`` when it claims more)."""
    mtype, counter, dgram, items, tc, char, segs, props, fingers, size = unpack_header(data)
    return MvnHeader(mtype, counter, dgram & 0x7F, bool(dgram & LAST_PIECE), items, tc, char, segs, props, fingers,
                     size)  # fmt: skip


# ------------------------------------------------------------------------------ segment names
#: The 20 finger-tracking segments of one hand, in the order MVN sends them (spec table 2).
FINGER_PARTS = (
    "Carpus", "FirstMetacarpal", "FirstProximalPhalange", "FirstDistalPhalange",
    "SecondMetacarpal", "SecondProximalPhalange", "SecondMiddlePhalange", "SecondDistalPhalange",
    "ThirdMetacarpal", "ThirdProximalPhalange", "ThirdMiddlePhalange", "ThirdDistalPhalange",
    "FourthMetacarpal", "FourthProximalPhalange", "FourthMiddlePhalange", "FourthDistalPhalange",
    "FifthMetacarpal", "FifthProximalPhalange", "FifthMiddlePhalange", "FifthDistalPhalange",
)  # fmt: skip
#: Names of the 40 finger segments: ``Left<part>`` (20) then ``Right<part>`` (20), e.g.
#: ``LeftCarpus``, ``RightSecondMiddlePhalange``.
FINGER_SEGMENTS = tuple(f"{side}{part}" for side in ("Left", "Right") for part in FINGER_PARTS)


@functools.lru_cache(maxsize=1024)
def segment_name(seg_id: int, props: int = 0, fingers: int = 0) -> str:
    """Name of segment ID ``seg_id`` in a message whose header counts ``props`` props and
    ``fingers`` finger segments (rules in the module docstring); ``Segment<ID>`` if unknown."""
    if 1 <= seg_id <= BODY_SEGMENT_COUNT:
        return MVN_SEGMENTS[seg_id - 1]
    first_finger = BODY_SEGMENT_COUNT + 1 + props
    if fingers > 0 and first_finger <= seg_id < first_finger + min(fingers, len(FINGER_SEGMENTS)):
        return FINGER_SEGMENTS[seg_id - first_finger]
    if BODY_SEGMENT_COUNT < seg_id <= BODY_SEGMENT_COUNT + len(PROP_SEGMENTS):
        return PROP_SEGMENTS[seg_id - BODY_SEGMENT_COUNT - 1]
    return f"Segment{seg_id}"


@functools.lru_cache(maxsize=256)
def _layout(id_bytes: bytes, props: int, fingers: int) -> tuple[np.ndarray, tuple[str, ...]]:
    """Segment IDs -> (read-only int64 IDs, names), cached per layout. ``id_bytes``: the N IDs'
    big-endian bytes grouped by byte position (all first bytes, then all second bytes, ...), which
    is what slicing a payload with the item size as step gives."""
    ids = np.frombuffer(id_bytes, dtype=np.uint8).reshape(4, -1).T.copy().view(">i4").ravel().astype(np.int64)
    ids.flags.writeable = False
    return ids, tuple(segment_name(i, props, fingers) for i in ids.tolist())


def _id_key(ids_be: np.ndarray) -> bytes:
    """The :func:`_layout` key of big-endian i32 IDs ``(N,)``."""
    return np.ascontiguousarray(ids_be, dtype=">i4").view(np.uint8).reshape(-1, 4).T.tobytes()


def segment_names(ids, props: int = 0, fingers: int = 0) -> tuple[str, ...]:
    """Names of segment IDs ``ids (N,)`` in a message with ``props`` props and ``fingers`` finger
    segments (cached per layout: a stream repeats the same IDs)."""
    return _layout(_id_key(np.asarray(ids)), int(props), int(fingers))[1]


# ------------------------------------------------------------------------------ fixed-size items
#: Big-endian numpy layouts of the fixed-size items (itemsize = :data:`ITEM_SIZES`).
POSE_DTYPE = np.dtype([("id", ">i4"), ("values", ">f4", (7,))])  # id, position, quaternion re i j k
JOINT_ANGLE_DTYPE = np.dtype([("parent", ">i4"), ("child", ">i4"), ("angles", ">f4", (3,))])
LINEAR_KINEMATICS_DTYPE = np.dtype([("id", ">i4"), ("values", ">f4", (9,))])  # position, velocity, acceleration
ANGULAR_KINEMATICS_DTYPE = np.dtype([("id", ">i4"), ("values", ">f4", (10,))])  # quaternion, ang. vel., ang. acc.
CENTER_OF_MASS_DTYPE = np.dtype([("values", ">f4", (3,))])

# Z-up rows -> Y-up rows: p_yup = p_zup @ _P (the rotation ZUP_TO_YUP, (x, y, z) -> (x, z, -y)).
_P = np.ascontiguousarray(ZUP_TO_YUP.T)
# Z-up (re, i, j, k) rows -> Y-up (x, y, z, w) rows: the inverse of to_zup_wxyz, i.e. the quaternion
# of ZUP_TO_YUP (-90 deg about X) times q: x = h(i - re), y = h(j + k), z = h(k - j), w = h(re + i).
_H = math.sqrt(0.5)
_Q = np.array([[-_H, 0.0, 0.0, _H], [_H, 0.0, 0.0, _H], [0.0, _H, -_H, 0.0], [0.0, _H, _H, 0.0]])
# One type-02 item as 8 float64 (the ID column unused) -> [position (3), quaternion xyzw (4)].
_POSE_MAP = np.zeros((8, 7))
_POSE_MAP[1:4, :3] = _P
_POSE_MAP[4:, 3:] = _Q
#: Largest deviation from 1 of the quaternions' squared norms before a message is rejected: per
#: quaternion for type 22; for type 02 (the hot path) of their sum over the message. MVN sends
#: them normalised; float32 rounding is ~1e-7 per quaternion.
QUATERNION_NORM_TOLERANCE = 1e-3


def _items(payload: bytes, items: int, dtype: np.dtype, what: str) -> np.ndarray:
    if items * dtype.itemsize != len(payload):
        raise MvnFormatError(f"{what}: {items} items of {dtype.itemsize} bytes do not fill the "
                             f"{len(payload)}-byte payload")  # fmt: skip
    return np.frombuffer(payload, dtype=dtype)


def _finite(values: np.ndarray, what: str) -> np.ndarray:
    if not np.isfinite(values).all():
        raise MvnFormatError(f"{what} holds non-finite values")
    return values


def _quaternions(wxyz: np.ndarray, what: str) -> np.ndarray:
    """Z-up (re, i, j, k) ``(N, 4)`` -> Y-up (x, y, z, w), rejecting non-unit ones."""
    dev = np.abs(np.einsum("ij,ij->i", wxyz, wxyz) - 1.0)
    if len(dev) and not dev.max() <= QUATERNION_NORM_TOLERANCE:
        raise MvnFormatError(f"{what}: a quaternion's squared norm is off 1 by {dev.max():.3g}")
    return wxyz @ _Q


class MvnPose(NamedTuple):
    """Type-02 payload: ``segment_ids (N,)`` int64 and their ``segment_names`` (see
    :func:`segment_name`), ``positions (N, 3)`` m and ``orientations (N, 4)`` (x, y, z, w), float64,
    Y-up world frame. ``segment_ids`` is shared between messages of one layout (read-only)."""

    segment_ids: np.ndarray
    segment_names: tuple[str, ...]
    positions: np.ndarray
    orientations: np.ndarray


def decode_pose(payload: bytes, items: int, props: int = 0, fingers: int = 0) -> MvnPose:
    """Inverse of :func:`encode_pose` for one whole (reassembled) type-02 message of ``items``
    segments; ``props`` and ``fingers`` (header counts) name the segments. Raises
    :class:`MvnFormatError` if the items do not fill the payload exactly, a value is not finite, or
    the quaternions' squared norms sum to more than :data:`QUATERNION_NORM_TOLERANCE` off ``items``.

    Vectorised: one pass of numpy over the whole message, no per-segment Python."""
    if items * POSE_QUATERNION_ITEM.size != len(payload) or items == 0:
        raise MvnFormatError(f"type 02: {items} items of 32 bytes do not fill the {len(payload)}-byte payload")
    v = np.ndarray((items, 8), ">f4", payload).astype(np.float64)  # column 0: the ID's bits, unused
    d = (v.T @ v).ravel()[::9].tolist()  # per column, the sum of squares (not finite if a value is not)
    if not math.isfinite(sum(d)):
        raise MvnFormatError("type 02 holds non-finite values (or a segment ID that reads as one)")
    q2 = d[4] + d[5] + d[6] + d[7]
    if not abs(q2 - items) <= QUATERNION_NORM_TOLERANCE:
        raise MvnFormatError(f"type 02: quaternions not of unit norm (squared norms sum to {q2:.6g} for {items})")
    out = v @ _POSE_MAP
    ids, names = _layout(payload[0::32] + payload[1::32] + payload[2::32] + payload[3::32], props, fingers)
    return MvnPose(ids, names, out[:, :3], out[:, 3:])


class MvnJointAngles(NamedTuple):
    """Type-20 payload: ``parent_point_ids`` and ``child_point_ids (J,)`` int64 (``256 * segment
    ID + local point ID``), ``angles (J, 3)`` rotations about the segment's x, y, z, radians."""

    parent_point_ids: np.ndarray
    child_point_ids: np.ndarray
    angles: np.ndarray


def decode_joint_angles(payload: bytes, items: int) -> MvnJointAngles:
    """Type-20 joint angles (20 bytes per joint: i32 parent point, i32 child point, 3 f32
    degrees -> radians)."""
    arr = _items(payload, items, JOINT_ANGLE_DTYPE, "type 20")
    angles = _finite(arr["angles"].astype(np.float64), "type 20")
    return MvnJointAngles(arr["parent"].astype(np.int64), arr["child"].astype(np.int64), np.radians(angles))


class MvnLinearKinematics(NamedTuple):
    """Type-21 payload: ``segment_ids (N,)`` and ``segment_names``, ``positions`` m, ``velocities`` m/s and
    ``accelerations`` m/s^2, each ``(N, 3)`` in the Y-up world frame."""

    segment_ids: np.ndarray
    segment_names: tuple[str, ...]
    positions: np.ndarray
    velocities: np.ndarray
    accelerations: np.ndarray


def decode_linear_kinematics(payload: bytes, items: int, props: int = 0, fingers: int = 0) -> MvnLinearKinematics:
    """Type-21 linear segment kinematics (40 bytes per segment: i32 ID, 9 f32), Z-up -> Y-up."""
    arr = _items(payload, items, LINEAR_KINEMATICS_DTYPE, "type 21")
    ids, names = _layout(_id_key(arr["id"]), props, fingers)
    v = _finite(arr["values"].astype(np.float64), "type 21").reshape(-1, 3, 3) @ _P
    return MvnLinearKinematics(ids, names, v[:, 0].copy(), v[:, 1].copy(), v[:, 2].copy())


class MvnAngularKinematics(NamedTuple):
    """Type-22 payload: ``segment_ids (N,)`` and ``segment_names``, ``orientations (N, 4)``
    (x, y, z, w), world ``angular_velocities`` rad/s and ``angular_accelerations`` rad/s^2
    ``(N, 3)``, Y-up."""

    segment_ids: np.ndarray
    segment_names: tuple[str, ...]
    orientations: np.ndarray
    angular_velocities: np.ndarray
    angular_accelerations: np.ndarray


def decode_angular_kinematics(payload: bytes, items: int, props: int = 0, fingers: int = 0) -> MvnAngularKinematics:
    """Type-22 angular segment kinematics (44 bytes per segment: i32 ID, quaternion (re, i, j, k),
    angular velocity, angular acceleration), Z-up -> Y-up."""
    arr = _items(payload, items, ANGULAR_KINEMATICS_DTYPE, "type 22")
    v = _finite(arr["values"].astype(np.float64), "type 22")
    ids, names = _layout(_id_key(arr["id"]), props, fingers)
    rates = v[:, 4:].reshape(-1, 2, 3) @ _P
    return MvnAngularKinematics(ids, names, _quaternions(v[:, :4], "type 22"), rates[:, 0].copy(), rates[:, 1].copy())


def decode_center_of_mass(payload: bytes, items: int) -> np.ndarray:
    """Type-24 centre of mass: one 12-byte item (3 f32, m, Z-up) -> position ``(3,)`` Y-up."""
    if items != 1:
        raise MvnFormatError(f"type 24 carries one centre of mass, the header counts {items} items")
    arr = _items(payload, items, CENTER_OF_MASS_DTYPE, "type 24")
    return _finite(arr["values"][0].astype(np.float64), "type 24") @ _P


# ------------------------------------------------------------------------------ strings
_I32 = struct.Struct(">i")


def read_string(payload: bytes, offset: int) -> tuple[str, int]:
    """The MVN string (i32 length + UTF-8) at ``offset``; returns it and the offset after it.
    The length is checked against the bytes left before anything is read."""
    if offset + 4 > len(payload):
        raise MvnFormatError(f"string length at byte {offset} runs past the {len(payload)}-byte payload",
                             truncated=True)  # fmt: skip
    (n,) = _I32.unpack_from(payload, offset)
    offset += 4
    if n < 0 or n > len(payload) - offset:
        raise MvnFormatError(f"string of {n} bytes at byte {offset - 4} does not fit the "
                             f"{len(payload) - offset} bytes left")  # fmt: skip
    try:
        return bytes(payload[offset:offset + n]).decode("utf-8"), offset + n
    except UnicodeDecodeError:
        raise MvnFormatError(f"string at byte {offset - 4} is not UTF-8") from None


def _whole_string(payload: bytes, what: str) -> str:
    text, end = read_string(payload, 0)
    if end != len(payload):
        raise MvnFormatError(f"{what}: {len(payload) - end} bytes follow the string")
    return text


def decode_meta(payload: bytes) -> dict[str, str]:
    """Type-12 meta data: ``{tag: value}`` in the order sent (tags ``name``, ``xmid``, ``color``
    and any other). Lines without ``:`` are skipped (the spec asks receivers to be lenient)."""
    out: dict[str, str] = {}
    for line in _whole_string(payload, "type 12").split("\n"):
        tag, colon, value = line.partition(":")
        if colon and tag:
            out[tag] = value
    return out


_TIME_CODE = re.compile(r"(\d{2}):([0-5]\d):([0-5]\d)\.(\d{3})")


def decode_time_code(payload: bytes) -> tuple[str, int]:
    """Type-25 time code: the text ``HH:MM:SS.mmm`` and its value in ms since midnight."""
    text = _whole_string(payload, "type 25")
    m = _TIME_CODE.fullmatch(text)
    if m is None:
        raise MvnFormatError(f"time code {text[:40]!r} is not HH:MM:SS.mmm")
    h, mi, s, ms = map(int, m.groups())
    return text, ((h * 60 + mi) * 60 + s) * 1000 + ms


class MvnScale(NamedTuple):
    """Type-13 payload: ``segment_names`` and ``segment_origins (S, 3)`` m (null pose, Y-up),
    and ``points`` (:class:`ScalePoint`, positions relative to the segment origin, Y-up)."""

    segment_names: tuple[str, ...]
    segment_origins: np.ndarray
    points: tuple[ScalePoint, ...]


_SCALE_POINT_MIN = _SCALE_POINT_IDS.size + 4 + _SCALE_FLAGS.size + _SCALE_VEC.size  # 24: empty name


def decode_scale(payload: bytes) -> MvnScale:
    """Inverse of one message of :func:`encode_scale`: ``i32 S``, S x (name, origin), ``i32 P``,
    P x (u16 segment ID, u16 point ID, name, u32 flags, position). Counts are checked against the
    bytes left before any item is read; trailing bytes are an error."""
    n = len(payload)
    if n < 4:
        raise MvnFormatError(f"type 13 payload of {n} bytes has no segment count", truncated=True)
    (s_count,) = _I32.unpack_from(payload, 0)
    off = 4
    if s_count < 0 or s_count * (4 + _SCALE_VEC.size) > n - off:
        raise MvnFormatError(f"type 13 segment count {s_count} does not fit {n - off} bytes")
    names, origins = [], np.empty((s_count, 3))
    for k in range(s_count):
        name, off = read_string(payload, off)
        if off + _SCALE_VEC.size > n:
            raise MvnFormatError(f"type 13 origin of {name!r} runs past the payload", truncated=True)
        names.append(name)
        origins[k] = _SCALE_VEC.unpack_from(payload, off)
        off += _SCALE_VEC.size
    if off + 4 > n:
        raise MvnFormatError("type 13 point count runs past the payload", truncated=True)
    (p_count,) = _I32.unpack_from(payload, off)
    off += 4
    if p_count < 0 or p_count * _SCALE_POINT_MIN > n - off:
        raise MvnFormatError(f"type 13 point count {p_count} does not fit {n - off} bytes")
    raw_points = []
    for _ in range(p_count):
        if off + _SCALE_POINT_IDS.size > n:
            raise MvnFormatError("type 13 point runs past the payload", truncated=True)
        seg, pid = _SCALE_POINT_IDS.unpack_from(payload, off)
        name, off = read_string(payload, off + _SCALE_POINT_IDS.size)
        if off + _SCALE_FLAGS.size + _SCALE_VEC.size > n:
            raise MvnFormatError(f"type 13 point {name!r} runs past the payload", truncated=True)
        (flags,) = _SCALE_FLAGS.unpack_from(payload, off)
        raw_points.append((seg, pid, name, flags, _SCALE_VEC.unpack_from(payload, off + _SCALE_FLAGS.size)))
        off += _SCALE_FLAGS.size + _SCALE_VEC.size
    if off != n:
        raise MvnFormatError(f"type 13: {n - off} bytes follow the last point")
    _finite(origins, "type 13 origins")
    pos = _finite(np.array([p[4] for p in raw_points], dtype=np.float64).reshape(-1, 3), "type 13 points") @ _P
    points = tuple(ScalePoint(seg, pid, name, flags, tuple(pos[k].tolist()))
                   for k, (seg, pid, name, flags, _) in enumerate(raw_points))  # fmt: skip
    return MvnScale(tuple(names), origins @ _P, points)

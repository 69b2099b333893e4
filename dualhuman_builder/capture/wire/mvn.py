"""Xsens MVN real-time network stream ("MXTP") datagrams: encoders for types 02, 12, 13 and 25.

Layout (``shared/reference/capture-protocols.md``; all fields **big-endian**): every datagram is a
24-byte :data:`HEADER` ``'>6sIBBIBBBBHH'`` — ID string ``b"MXTP" + two ASCII digits`` of the
message type, sample counter (u32), datagram counter (u8), number of items in this datagram (u8),
time code (u32, ms since the start of the recording clock), character ID (u8), number of body
segments (u8), props (u8), finger segments (u8), reserved (u16, zero), payload size (u16, bytes
after the header) — followed by the payload.

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
  terminator) and the reference give the prefixed form. Hours wrap at 24.
* **Point IDs** (100*seg+pt vs 256*seg+pt) do not arise: type 13 sends the segment ID and the
  point's local ID as two separate u16 fields. Type 23 (item size 44 vs 68) is not encoded.

Frames: samples are Y-up (:mod:`dualhuman_builder.conventions`); types 02 and 13 are MVN's
**Z-up**, right-handed frame. Positions go through the inverse of ``ZUP_TO_YUP``
(``(x, y, z) -> (x, -z, y)``) and orientations are left-multiplied by it
(:func:`~dualhuman_builder.capture.wire.to_zup_wxyz`), quaternions sent as ``(re, i, j, k)``.
A body facing our +X stands in MVN's null pose (all segment orientations identity).
"""

from __future__ import annotations

import re
import struct
from dataclasses import dataclass
from enum import IntEnum
from typing import Iterable, Mapping, Sequence

import numpy as np

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.samples import SuitFrame
from dualhuman_builder.capture.wire import check_finite, check_unit_quaternions, to_zup_wxyz
from dualhuman_builder.conventions import yup_to_zup_points

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

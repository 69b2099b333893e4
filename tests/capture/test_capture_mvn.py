"""The MVN network-stream source: payload decoders against hand-packed bytes, and the decoder on
real UDP sockets on loopback fed by the simulated suits (two characters on one port, split
messages, seeded faults checked against the player's FaultLog, stale and recomposed characters,
sender allow-list)."""

from __future__ import annotations

import functools
import math
import socket
import struct
import time
from collections import Counter, defaultdict

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.mvn_udp import (CONFIRM, JUMP_GAP, MAX_CANDIDATES, MAX_PENDING, MAX_PENDING_BYTES,
                                              SEEN_WINDOW, WINDOW, MvnDecoder, MvnUdpSource)  # fmt: skip
from dualhuman_builder.capture.samples import (AngularSegmentKinematics, CenterOfMass, JointAngles,
                                               LinearSegmentKinematics, SuitFrame, SuitMeta, SuitScale,
                                               SuitTimeCode)  # fmt: skip
from dualhuman_builder.capture.sources import RawPacket, SourceError, make_decoder, now_ns, open_source
from dualhuman_builder.capture.wire.mvn import (
    ITEM_SIZES, ANGULAR_KINEMATICS_DTYPE, CENTER_OF_MASS_DTYPE, FINGER_SEGMENTS, JOINT_ANGLE_DTYPE,
    LINEAR_KINEMATICS_DTYPE, POSE_DTYPE, MvnFormatError, MvnMessageType, ScalePoint, decode_angular_kinematics,
    decode_center_of_mass, decode_joint_angles, decode_linear_kinematics, decode_meta, decode_pose, decode_scale,
    decode_time_code, encode_frame, encode_meta, encode_pose, encode_scale, encode_time_code, parse_header,
    segment_names, time_code_text,
)  # fmt: skip
from dualhuman_builder.conventions import ZUP_TO_YUP
from dualhuman_builder.sim.devices import Faults, Outage, UdpPlayer, merge, mvn_packets
from dualhuman_builder.sim.kinematics import DeviceClock
from dualhuman_builder.sim.suit import simulate_suit
from dualhuman_builder.tracks import SkeletonTrack

HEADER = ">6sIBBIBBBBHH"  # the MVN spec's header layout, written out here on purpose


def _datagram(mtype: int, payload: bytes, *, items: int, counter=0, dgram=0x80, tc=0, char=0, segs=23, props=0,
              fingers=0, size=None) -> bytes:  # fmt: skip
    head = struct.pack(HEADER, b"MXTP%02d" % mtype, counter, dgram, items, tc, char, segs, props, fingers, 0,
                       len(payload) if size is None else size)  # fmt: skip
    return head + payload


def _yup(v):  # MVN's Z-up (x, y, z) is our Y-up (x, z, -y)
    v = np.asarray(v, dtype=np.float64)
    return np.stack([v[..., 0], v[..., 2], -v[..., 1]], axis=-1)


def _yup_quat(wxyz):  # Z-up (re, i, j, k) -> Y-up (x, y, z, w): R_yup = ZUP_TO_YUP @ R_zup
    w, x, y, z = np.asarray(wxyz, dtype=np.float64).T
    return (Rotation.from_matrix(ZUP_TO_YUP) * Rotation.from_quat(np.stack([x, y, z, w], -1))).as_quat()


def _same_rotation(a, b, atol=2e-6):
    a, b = np.asarray(a), np.asarray(b)
    dots = np.abs(np.sum(a * b, axis=-1))  # q and -q are one rotation
    np.testing.assert_allclose(dots, 1.0, atol=atol)


# ------------------------------------------------------------------------------------ streams
def _track(frames=16, fps=30.0) -> SkeletonTrack:
    """A tiny synthetic 23-segment track: every segment yawing and sliding (0.5 s at 30 fps)."""
    t = np.arange(frames) / fps
    base = Rotation.random(23, random_state=1)
    quat = np.stack([(Rotation.from_rotvec(np.outer(0.3 * np.sin(t + i), [0, 1, 0])) * base[i]).as_quat()
                     for i in range(23)], 1)  # fmt: skip
    pos = np.stack([np.outer(np.ones(frames), [0.1 * i, 1.0 + 0.01 * i, 0.0]) + np.outer(t, [0.2, 0, 0])
                    for i in range(23)], 1)  # fmt: skip
    ns = np.round(t * 1e9).astype(np.int64)
    return SkeletonTrack(MVN_SEGMENTS, quat, pos, ns, ns, actor="synth", fps=fps)


@pytest.fixture(scope="module")
def suits():
    """Two actors' simulated suits at 240 Hz (about 120 samples each) on different device clocks."""
    gt = _track()
    return (simulate_suit(gt, character=0, seed=1, clock=DeviceClock(offset_s=3.25, drift_ppm=40)),
            simulate_suit(gt, character=1, seed=1, clock=DeviceClock(offset_s=71.5, drift_ppm=-25)))  # fmt: skip


def _receive(url: str, packets, *, faults=None, speed=math.inf, sock=None):
    """Play ``packets`` to a fresh source for ``url`` on loopback; returns (samples, source, report).
    The source is closed; its decoder has seen every datagram and ``finish``."""
    src = open_source(url)
    out = []
    try:
        player = UdpPlayer(("127.0.0.1", src.port), speed=speed, faults=faults, sock=sock).add(packets)
        with player:
            player.start()
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline:
                got = src.read(0.02)
                for p in got:
                    out += src.decoder.feed(p)
                if not got and not player.running:
                    break
            report = player.join()
        for p in src.read(0.05):
            out += src.decoder.feed(p)
        out += src.decoder.finish()
        assert report.completed and report.send_errors == 0
        stats = src.stats()
        assert stats.get("kernel_drops", 0) == 0, "the kernel dropped datagrams: counts below would be off"
    finally:
        src.close()
    return out, src, report


def _frames(samples, cls=SuitFrame):
    by_char = defaultdict(list)
    for s in samples:
        if isinstance(s, cls):
            by_char[s.character].append(s)
    return by_char


def _check_frame(got: SuitFrame, suit, k: int, t0_ns: int):
    assert got.sample_counter == int(suit.sample_counter[k]) and got.character == suit.character
    assert got.time_code_ms == int(suit.time_code_ms[k])
    # the wire carries MVN's ms time code only: device time = time code (ms since the first sample)
    assert got.device_time_ns == int(suit.time_code_ms[k]) * 1_000_000
    assert 0 <= (int(suit.device_time_ns[k]) - int(suit.device_time_ns[0])) - got.device_time_ns < 1_000_000
    assert got.host_time_ns >= t0_ns and isinstance(got.host_time_ns, int)
    assert got.segment_names == MVN_SEGMENTS
    assert got.positions.shape == (23, 3) and got.orientations.shape == (23, 4)
    assert got.positions.dtype == np.float64 and got.orientations.dtype == np.float64
    np.testing.assert_allclose(got.positions, suit.positions[k], atol=2e-6, rtol=0)  # float32 on the wire
    np.testing.assert_allclose(got.orientations, suit.orientations[k], atol=2e-7, rtol=0)


# ------------------------------------------------------------------------------------ header
def test_parse_header_fields_and_every_rejection():
    (d,) = encode_pose(SuitFrame(7, 0x01020304, 56789, 0, 0, MVN_SEGMENTS, np.tile([0, 0, 0, 1.0], (23, 1)),
                                 np.zeros((23, 3))))  # fmt: skip
    h = parse_header(d)
    assert (h.message_type, h.sample_counter, h.datagram_index, h.last_piece, h.items, h.time_code_ms) == (
        2, 0x01020304, 0, True, 23, 56789)
    assert (h.character, h.segments, h.props, h.fingers, h.payload_size) == (7, 23, 0, 0, 736)
    piece = parse_header(_datagram(13, b"xy", items=0, dgram=0x03))
    assert (piece.message_type, piece.datagram_index, piece.last_piece) == (13, 3, False)

    with pytest.raises(MvnFormatError, match="shorter than the 24-byte") as e:
        parse_header(d[:23])
    assert e.value.truncated and isinstance(e.value, ValueError)
    with pytest.raises(MvnFormatError, match="bad ID string") as e:
        parse_header(b"MXTQ" + d[4:])
    assert not e.value.truncated
    with pytest.raises(MvnFormatError, match="bad ID string"):
        parse_header(d[:4] + b"0x" + d[6:])
    with pytest.raises(MvnFormatError, match="says 736 bytes but 700 follow") as e:
        parse_header(d[:724])
    assert e.value.truncated
    with pytest.raises(MvnFormatError, match="says 736 bytes but 737 follow") as e:
        parse_header(d + b"\0")
    assert not e.value.truncated
    with pytest.raises(MvnFormatError, match="says 65535 bytes but 4 follow"):
        parse_header(_datagram(2, b"\0" * 4, items=1, size=0xFFFF))


# ------------------------------------------------------------------------------------ payloads
def test_pose_decoder_inverts_the_encoder_with_props_and_rejects_bad_items():
    names = MVN_SEGMENTS + ("Prop1", "Prop2")
    q = Rotation.random(25, random_state=3).as_quat()
    p = np.random.default_rng(3).uniform(-3, 3, (25, 3))
    (d,) = encode_pose(SuitFrame(1, 5, 9, 0, 0, names, q, p))
    h = parse_header(d)
    pose = decode_pose(d[24:], h.items, h.props, h.fingers)
    assert pose.segment_names == names and pose.segment_ids.tolist() == list(range(1, 26))
    np.testing.assert_allclose(pose.positions, p, atol=2e-6, rtol=0)
    np.testing.assert_allclose(pose.orientations, q, atol=2e-7, rtol=0)
    # the payload read independently: Z-up metres and (re, i, j, k)
    seg, *vals = struct.unpack(">i7f", d[24 + 32 * 7:24 + 32 * 8])
    np.testing.assert_allclose(_yup(vals[:3]), pose.positions[7], atol=1e-12)
    _same_rotation(_yup_quat(vals[3:]), pose.orientations[7])

    with pytest.raises(MvnFormatError, match="24 items of 32 bytes do not fill"):
        decode_pose(d[24:], 24)
    with pytest.raises(MvnFormatError, match="255 items"):
        decode_pose(d[24:], 255)
    with pytest.raises(MvnFormatError, match="0 items"):
        decode_pose(b"", 0)
    bad = bytearray(d[24:])
    bad[4:8] = struct.pack(">f", math.nan)
    with pytest.raises(MvnFormatError, match="non-finite"):
        decode_pose(bytes(bad), 25)
    bad = bytearray(d[24:])
    bad[16:20] = struct.pack(">f", 1.5)  # a quaternion's real part: no longer unit norm
    with pytest.raises(MvnFormatError, match="unit norm"):
        decode_pose(bytes(bad), 25)


def test_segment_names_body_props_fingers():
    assert segment_names(range(1, 24)) == MVN_SEGMENTS
    assert segment_names([24, 27]) == ("Prop1", "Prop4")  # no fingers: 24..27 are props
    # with gloves the finger segments follow the props (spec table 2: left carpus = 23 + props)
    assert segment_names([24, 25, 26, 45, 64], props=1, fingers=40) == (
        "Prop1", "LeftCarpus", "LeftFirstMetacarpal", "RightCarpus", "RightFifthDistalPhalange")
    assert segment_names([24, 63, 64, 0, -3], fingers=40) == (
        "LeftCarpus", "RightFifthDistalPhalange", "Segment64", "Segment0", "Segment-3")
    assert len(set(FINGER_SEGMENTS)) == 40


def test_meta_scale_and_time_code_decoders():
    (m,) = encode_meta(2, name="alice", xmid="00B4A1F2", color="ff8800", extra={"scene": "hug"})
    assert decode_meta(m[24:]) == {"name": "alice", "xmid": "00B4A1F2", "color": "FF8800", "scene": "hug"}
    text = "name:bob\nnonsense line\nunknown:x:y\n"
    assert decode_meta(struct.pack(">i", len(text)) + text.encode()) == {"name": "bob", "unknown": "x:y"}
    for payload, match in [(struct.pack(">i", 0x7FFFFFFF) + b"name:a\n", "does not fit"),
                           (struct.pack(">i", -1), "does not fit"), (b"\0\0", "runs past"),
                           (struct.pack(">i", 2) + b"\xff\xfe", "not UTF-8"),
                           (struct.pack(">i", 1) + b"ab", "1 bytes follow")]:  # fmt: skip
        with pytest.raises(MvnFormatError, match=match):
            decode_meta(payload)

    (t,) = encode_time_code(3_723_456)
    assert decode_time_code(t[24:]) == ("01:02:03.456", 3_723_456)
    (t,) = encode_time_code(25 * 3_600_000 + 1)  # hours wrap at 24
    assert decode_time_code(t[24:]) == ("01:00:00.001", 3_600_001)
    for bad in ("1:02:03.456", "01:62:03.456", "01:02:03,456", "01:02:03.4567"):
        with pytest.raises(MvnFormatError, match="HH:MM:SS.mmm"):
            decode_time_code(struct.pack(">i", len(bad)) + bad.encode())

    origins = {name: (0.01 * i, 0.9 + 0.01 * i, -0.02 * i) for i, name in enumerate(MVN_SEGMENTS)}
    points = [ScalePoint(1 + i % 23, i, f"pt{i}", 1 << (i % 3), (0.0, 0.05 * i, 0.1)) for i in range(30)]
    msgs = encode_scale(5, origins, points, max_datagram=400)
    by_counter = defaultdict(list)
    for d in msgs:
        by_counter[parse_header(d).sample_counter].append(d)
    decoded = [decode_scale(b"".join(x[24:] for x in sorted(v, key=lambda x: x[10] & 0x7F)))
               for _, v in sorted(by_counter.items())]  # fmt: skip
    assert decoded[0].segment_names == MVN_SEGMENTS and decoded[0].points == ()
    np.testing.assert_allclose(decoded[0].segment_origins, np.array(list(origins.values())), atol=1e-6)
    got = [p for s in decoded[1:] for p in s.points]
    assert all(s.segment_names == () and s.segment_origins.shape == (0, 3) for s in decoded[1:])
    assert [(p.segment_id, p.point_id, p.name, p.flags) for p in got] == [
        (p.segment_id, p.point_id, p.name, p.flags) for p in points]
    np.testing.assert_allclose([p.position for p in got], [p.position for p in points], atol=1e-6)
    with pytest.raises(MvnFormatError, match="segment count 2147483647 does not fit"):
        decode_scale(struct.pack(">i", 0x7FFFFFFF) + b"\0" * 40)
    with pytest.raises(MvnFormatError, match="point count 100 does not fit"):
        decode_scale(struct.pack(">ii", 0, 100) + b"\0" * 40)
    with pytest.raises(MvnFormatError, match="bytes follow the last point"):
        decode_scale(struct.pack(">ii", 0, 0) + b"\0")


def test_fixed_size_types_20_21_22_24():
    assert {t: d.itemsize for t, d in [(MvnMessageType.POSE_QUATERNION, POSE_DTYPE),
                                       (MvnMessageType.JOINT_ANGLES, JOINT_ANGLE_DTYPE),
                                       (MvnMessageType.LINEAR_KINEMATICS, LINEAR_KINEMATICS_DTYPE),
                                       (MvnMessageType.ANGULAR_KINEMATICS, ANGULAR_KINEMATICS_DTYPE),
                                       (MvnMessageType.CENTER_OF_MASS, CENTER_OF_MASS_DTYPE)]} == {
        t: ITEM_SIZES[t] for t in (2, 20, 21, 22, 24)}  # fmt: skip
    rng = np.random.default_rng(11)
    # type 20: parent/child point IDs (256 * segment + local point) and three angles in degrees
    joints = [(256 * 1 + 13, 256 * 2 + 1, 10.0, -20.0, 30.0), (256 * 5 + 2, 256 * 6 + 1, 0.5, 90.0, -180.0)]
    ja = decode_joint_angles(b"".join(struct.pack(">ii3f", *j) for j in joints), 2)
    assert ja.parent_point_ids.tolist() == [269, 1282] and ja.child_point_ids.tolist() == [513, 1537]
    np.testing.assert_allclose(ja.angles, np.radians([j[2:] for j in joints]), atol=1e-7)
    # type 21: id, position, velocity, acceleration (Z-up)
    vals = rng.uniform(-5, 5, (3, 9)).astype(np.float32)
    lk = decode_linear_kinematics(b"".join(struct.pack(">i9f", i, *v) for i, v in zip((1, 7, 24), vals)), 3)
    assert lk.segment_names == ("Pelvis", "Head", "Prop1") and lk.segment_ids.tolist() == [1, 7, 24]
    for got, cols in ((lk.positions, slice(0, 3)), (lk.velocities, slice(3, 6)), (lk.accelerations, slice(6, 9))):
        np.testing.assert_array_equal(got, _yup(vals[:, cols].astype(np.float64)))
        assert got.shape == (3, 3) and got.flags.c_contiguous
    # type 22: id, quaternion (re, i, j, k), angular velocity, angular acceleration (Z-up)
    q = Rotation.random(2, random_state=4).as_quat()[:, [3, 0, 1, 2]]
    rates = rng.uniform(-9, 9, (2, 6))
    ak = decode_angular_kinematics(b"".join(struct.pack(">i10f", i, *q[k], *rates[k]) for k, i in enumerate((3, 23))), 2)
    assert ak.segment_names == ("L3", "LeftToe")
    _same_rotation(ak.orientations, _yup_quat(q))
    np.testing.assert_allclose(ak.angular_velocities, _yup(rates[:, :3]), atol=1e-5)
    np.testing.assert_allclose(ak.angular_accelerations, _yup(rates[:, 3:]), atol=1e-5)
    # type 24: one position
    np.testing.assert_allclose(decode_center_of_mass(struct.pack(">3f", 0.25, -0.5, 1.0), 1), [0.25, 1.0, 0.5])
    for fn, payload, items in [(decode_joint_angles, b"\0" * 20, 2), (decode_linear_kinematics, b"\0" * 44, 1),
                               (decode_angular_kinematics, b"\0" * 40, 1), (decode_center_of_mass, b"\0" * 24, 2),
                               (decode_center_of_mass, b"\0" * 11, 1)]:  # fmt: skip
        with pytest.raises(MvnFormatError):
            fn(payload, items)
    bad = struct.pack(">i10f", 1, 2.0, 0, 0, 0, 0, 0, 0, 0, 0, 0)
    with pytest.raises(MvnFormatError, match="squared norm"):
        decode_angular_kinematics(bad, 1)


def test_decoder_yields_typed_samples_for_every_type():
    dec = MvnUdpSource.make_decoder("mvn+udp://127.0.0.1:9763")
    q = Rotation.random(2, random_state=5).as_quat()[:, [3, 0, 1, 2]]
    datagrams = [
        *encode_meta(3, name="carol", xmid="00B4", color="00ff00", sample_counter=1, time_code_ms=40),
        *encode_scale(3, {"Pelvis": (0, 0.9, 0), "L5": (0, 1.0, 0)}, [ScalePoint(1, 13, "pSacrum", 2, (-0.1, 0, 0))],
                      sample_counter=2, time_code_ms=40),  # fmt: skip
        _datagram(20, struct.pack(">ii3f", 269, 513, 90.0, 0, 0), items=1, counter=3, tc=50, char=3),
        _datagram(21, struct.pack(">i9f", 1, *range(9)), items=1, counter=3, tc=50, char=3),
        _datagram(22, b"".join(struct.pack(">i10f", i + 1, *q[i], *range(6)) for i in range(2)), items=2, counter=3,
                  tc=50, char=3),  # fmt: skip
        _datagram(24, struct.pack(">3f", 1, 2, 3), items=1, counter=3, tc=50, char=3),
        *encode_time_code(61_001, character=3, sample_counter=3),
    ]
    out = [s for i, d in enumerate(datagrams) for s in dec.feed(RawPacket(1000 + i, d))]
    assert [type(s) for s in out] == [SuitMeta, SuitScale, SuitScale, JointAngles, LinearSegmentKinematics,
                                      AngularSegmentKinematics, CenterOfMass, SuitTimeCode]  # fmt: skip
    meta, seg, pts, ja, lin, ang, com, tc = out
    assert (meta.name, meta.xmid, meta.color, meta.tags) == ("carol", "00B4", "00FF00", ("name", "xmid", "color"))
    assert (meta.character, meta.sample_counter, meta.time_code_ms, meta.device_time_ns, meta.host_time_ns) == (
        3, 1, 40, 40_000_000, 1000)
    assert seg.segment_names == ("Pelvis", "L5") and seg.point_names == () and seg.sample_counter == 2
    np.testing.assert_allclose(seg.segment_origins, [[0, 0.9, 0], [0, 1.0, 0]], atol=1e-7)
    assert pts.point_names == ("pSacrum",) and pts.point_segment_ids.tolist() == [1] and pts.point_ids.tolist() == [13]
    assert pts.point_flags.tolist() == [2] and pts.point_positions.shape == (1, 3)
    np.testing.assert_allclose(pts.point_positions, [[-0.1, 0, 0]], atol=1e-7)
    np.testing.assert_allclose(ja.angles, [[math.pi / 2, 0, 0]], atol=1e-7)
    assert ja.device_time_ns == 50_000_000 and ja.host_time_ns == 1003
    assert lin.segment_names == ("Pelvis",)
    np.testing.assert_allclose(lin.velocities, [[3, 5, -4]])
    assert ang.segment_names == ("Pelvis", "L5") and ang.orientations.shape == (2, 4)
    np.testing.assert_allclose(com.position, [1, 3, -2])
    assert (tc.text, tc.time_of_day_ms, tc.time_code_ms, tc.device_time_ns) == ("00:01:01.001", 61_001, 61_001,
                                                                                 61_001_000_000)  # fmt: skip
    assert dec.status(1010)["mvn/3"]["name"] == "carol"
    assert dec.counters["samples"] == 8 and dec.counters["bad_payload"] == 0

    # unsupported and deprecated types are counted, one event per type; unknown ones too
    for mtype in (1, 3, 4, 5, 10, 11, 23, 1, 23, 99):
        assert dec.feed(RawPacket(2000, _datagram(mtype, b"\0" * 28, items=1, char=3))) == []
    assert dec.counters["unsupported_type"] == 10
    events = [e for e in dec.pop_events() if e.kind == "unsupported-type"]
    assert len(events) == 8 and "01 (pose euler)" in events[0].message and "99 (unknown)" in events[-1].message


def test_counters_and_time_code_unwrap_across_u32_wrap():
    dec = MvnDecoder()
    q, p = np.tile([0, 0, 0, 1.0], (23, 1)), np.zeros((23, 3))
    start_c, start_t = (1 << 32) - 3, (1 << 32) - 10
    got = []
    for k in range(6):
        frame = SuitFrame(0, start_c + k, start_t + 4 * k, 0, 0, MVN_SEGMENTS, q, p)  # the encoder wraps to u32
        for d in encode_frame(frame):
            got += dec.feed(RawPacket(k, d))
    frames = [s for s in got if isinstance(s, SuitFrame)]
    assert [f.sample_counter for f in frames] == [start_c + k for k in range(6)]
    assert [f.time_code_ms for f in frames] == [start_t + 4 * k for k in range(6)]
    assert np.all(np.diff([f.device_time_ns for f in frames]) == 4_000_000)
    assert dec.counters["lost"] == 0 and dec.counters["counter_resets"] == 0


def test_reassembly_duplicates_incomplete_and_eviction():
    dec = MvnDecoder()
    rng = np.random.default_rng(2)

    def pieces(counter, char=0):
        f = SuitFrame(char, counter, counter * 4, 0, 0, MVN_SEGMENTS, Rotation.random(23, random_state=counter).as_quat(),
                      rng.uniform(-1, 1, (23, 3)))  # fmt: skip
        return f, encode_pose(f, max_datagram=24 + 32 * 8)  # 3 pieces: 8, 8, 7 segments

    f0, p0 = pieces(0)
    assert [d[10] for d in p0] == [0x00, 0x01, 0x82]
    assert dec.feed(RawPacket(1, p0[2])) == [] and dec.feed(RawPacket(2, p0[0])) == []
    assert dec.feed(RawPacket(3, p0[0])) == []  # a duplicated piece
    (got,) = dec.feed(RawPacket(4, p0[1]))
    np.testing.assert_allclose(got.positions, f0.positions, atol=1e-6)
    assert got.host_time_ns == 4  # the datagram that completed the message
    assert dec.feed(RawPacket(5, p0[1])) == []  # a piece of a completed message
    assert dec.counters["duplicate"] == 2
    # a message missing a piece is dropped once one WINDOW counters newer completes
    _, p1 = pieces(1)
    dec.feed(RawPacket(6, p1[0]))
    for c in range(2, 2 + WINDOW):
        for d in pieces(c)[1]:
            dec.feed(RawPacket(7, d))
    assert dec.counters["incomplete"] == 0
    for d in pieces(2 + WINDOW)[1]:
        dec.feed(RawPacket(8, d))
    assert dec.counters["incomplete"] == 1 and dec.characters[0]["incomplete"] == 1
    assert dec.counters["lost"] == 1  # counter 1 never arrived whole
    # contradicting piece indices
    _, p = pieces(50)
    dec.feed(RawPacket(9, p[2]))
    dec.feed(RawPacket(9, p[2][:10] + bytes([0x83]) + p[2][11:]))  # a second "last" piece
    assert dec.counters["bad_header"] == 1
    # a flood of pieces that never complete: bounded, oldest evicted, the rest incomplete at the end
    for c in range(1000, 1100):
        dec.feed(RawPacket(10, _datagram(2, b"\0" * 32, items=1, counter=c, dgram=5, char=9)))
    assert dec.counters["evicted"] == 100 + 1 - 64 and len(dec._pending) == 64
    dec.finish()
    assert dec.counters["incomplete"] == 1 + 64 and not dec._pending


# ------------------------------------------------------------------------------------ UDP
def test_two_characters_on_one_port_split_messages_and_prologue(suits):
    s0, s1 = suits
    prologue0 = [*encode_meta(0, name="alice", max_datagram=300),
                 *encode_scale(0, {n: (0.0, 0.1 * i, 0.0) for i, n in enumerate(MVN_SEGMENTS)}, max_datagram=300)]
    prologue1 = encode_meta(1, name="bob", color="0000ff")
    packets = (mvn_packets(s0, clock="host", max_datagram=300, prologue=prologue0)  # 3 pieces per pose
               + mvn_packets(s1, clock="host", prologue=prologue1))  # fmt: skip
    assert max(len(p.data) for p in packets) <= 760 and sum(p.data[10] == 0x00 for p in packets) >= len(s0)
    t0 = now_ns()
    out, src, report = _receive("mvn+udp://127.0.0.1:0", packets)
    frames = _frames(out)
    assert sorted(frames) == [0, 1]
    for suit in (s0, s1):
        got = frames[suit.character]
        assert len(got) == len(suit) > 100
        for k, f in enumerate(got):
            _check_frame(f, suit, k, t0)
        assert np.all(np.diff([f.host_time_ns for f in got]) >= 0)
    # the characters really differ (each got its own stream, not the other's values)
    assert np.abs(frames[0][60].orientations - frames[1][60].orientations).max() > 1e-3
    tcs = _frames(out, SuitTimeCode)
    assert [t.text for t in tcs[1]] == [time_code_text(int(ms)) for ms in s1.time_code_ms]
    metas = _frames(out, SuitMeta)
    assert metas[0][0].name == "alice" and (metas[1][0].name, metas[1][0].color) == ("bob", "0000FF")
    (scale,) = _frames(out, SuitScale)[0]
    assert scale.segment_names == MVN_SEGMENTS
    np.testing.assert_allclose(scale.segment_origins[:, 1], 0.1 * np.arange(23), atol=1e-6)
    c = src.decoder.counters
    n = len(s0) + len(s1)
    assert c["packets"] == report.sent == len(packets) and c["frames"] == n
    assert c["samples"] == n + n + 2 + 1  # poses, time codes, meta, scale
    for name in ("truncated", "bad_header", "bad_payload", "incomplete", "evicted", "lost", "duplicate", "out_of_order",
                 "unsupported_type", "other_character", "segment_count_changes", "counter_resets"):  # fmt: skip
        assert c[name] == 0, name
    status = src.decoder.status(frames[1][-1].host_time_ns)
    assert set(status) == {"mvn/0", "mvn/1"}
    assert status["mvn/0"]["name"] == "alice" and status["mvn/1"]["segments"] == 23 and status["mvn/1"]["live"]
    assert 225 < status["mvn/0"]["rate_hz"] < 255  # 240 Hz on MVN's ms clock


def _pose_key(data: bytes):
    ident, counter, dgram, items, tc, char = struct.unpack(HEADER, data[:24])[:6]
    return ident, char, counter, dgram & 0x7F, bool(dgram & 0x80)


def _expected_from_log(player_packets, sent):
    """Per character, from the datagrams as they were sent: counters of complete pose messages,
    pose messages with some but not all pieces, and complete ones finished after a newer one."""
    n_pieces = Counter()
    for p in player_packets:
        ident, char, counter, _, _ = _pose_key(p.data)
        if ident == b"MXTP02":
            n_pieces[char, counter] += 1
    got = defaultdict(set)
    complete, newest, late = defaultdict(set), {}, Counter()
    for i in sent:
        ident, char, counter, index, _ = _pose_key(player_packets[i].data)
        if ident != b"MXTP02" or index in got[char, counter]:
            continue
        got[char, counter].add(index)
        if len(got[char, counter]) == n_pieces[char, counter]:
            complete[char].add(counter)
            if char in newest and counter < newest[char]:
                late[char] += 1
            newest[char] = max(newest.get(char, counter), counter)
    partial = sum(1 for k, v in got.items() if 0 < len(v) < n_pieces[k])
    lost = {c: max(s) - min(s) + 1 - len(s) for c, s in complete.items()}
    return complete, partial, lost, late


def test_loss_duplicates_and_reordering_match_the_fault_log(suits):
    s0, s1 = suits
    packets = mvn_packets(s0, clock="host", max_datagram=300) + mvn_packets(s1, clock="host")

    # loss: lost pose counters (whole or in part) between the first and last received
    out, src, report = _receive("mvn+udp://127.0.0.1:0", packets, faults=Faults(seed=7, loss=0.06))
    log = report.faults
    assert len(log.lost) > 10
    complete, partial, lost, _ = _expected_from_log(merge(packets), log.sent)
    frames = _frames(out)
    c = src.decoder.counters
    assert partial > 0 and c["incomplete"] == partial
    for ch in (0, 1):
        assert sorted(f.sample_counter for f in frames[ch]) == sorted(complete[ch])
        assert src.decoder.characters[ch]["lost"] == lost[ch] > 0
    assert c["lost"] == lost[0] + lost[1] and c["duplicate"] == 0 and c["out_of_order"] == 0
    assert c["packets"] == len(log.sent) == len(packets) - len(log.lost)

    # duplicates: every duplicated datagram counted once, no frame yielded twice
    out, src, report = _receive("mvn+udp://127.0.0.1:0", packets, faults=Faults(seed=8, duplicate=0.1))
    frames = _frames(out)
    assert len(report.faults.duplicated) > 20
    assert src.decoder.counters["duplicate"] == len(report.faults.duplicated)
    assert [f.sample_counter for f in frames[0]] == list(range(len(s0)))
    assert [f.sample_counter for f in frames[1]] == list(range(len(s1)))
    assert src.decoder.counters["lost"] == 0 and src.decoder.counters["incomplete"] == 0
    dups = sum(src.decoder.characters[ch]["duplicate"] for ch in (0, 1))
    assert dups == len(report.faults.duplicated)

    # reordering: late messages yielded and counted, taken back out of `lost`
    out, src, report = _receive("mvn+udp://127.0.0.1:0", packets,
                                faults=Faults(seed=9, reorder=0.15, max_displacement=8))  # fmt: skip
    complete, partial, _, late = _expected_from_log(merge(packets), report.faults.sent)
    frames = _frames(out)
    c = src.decoder.counters
    assert len(report.faults.reordered) > 20 and late[0] > 0 and late[1] > 0
    for ch, suit in ((0, s0), (1, s1)):
        assert sorted(f.sample_counter for f in frames[ch]) == list(range(len(suit)))
        assert src.decoder.characters[ch]["out_of_order"] == late[ch]
        assert src.decoder.characters[ch]["lost"] == 0
    assert c["out_of_order"] == late[0] + late[1] and c["lost"] == 0 and c["incomplete"] == 0 == partial
    assert c["duplicate"] == 0
    order = [f.sample_counter for f in frames[1]]
    assert order != sorted(order)  # yielded in arrival order
    by_counter = {f.sample_counter: f for f in frames[1]}
    for k in range(len(s1)):
        _check_frame(by_counter[k], s1, k, 0)


def test_corrupt_truncated_and_lying_datagrams_are_counted_never_raised(suits):
    s0, s1 = suits
    good = [p.data for p in mvn_packets([s1.frame(k) for k in range(3)], clock="host")]
    (pose,) = encode_pose(s1.frame(5))
    liars = [
        pose[:10],  # shorter than the header
        pose[:300],  # cut: payload size says 736
        _datagram(2, b"\0" * 100, items=3, size=0xFFFF),  # claims a 64 KiB payload
        pose[:11] + bytes([255]) + pose[12:],  # claims 255 segments
        pose[:11] + bytes([22]) + pose[12:],  # one segment too few for the bytes
        b"MXTQ" + pose[4:],  # not MXTP
        pose + b"\0\0",  # payload size shorter than the datagram
        _datagram(12, struct.pack(">i", 0x7FFFFFF0) + b"name:x\n", items=1, char=1),  # a 2 GiB string
        _datagram(13, struct.pack(">i", 0x7FFFFFFF), items=1, char=1),  # 2^31 segments
        _datagram(25, struct.pack(">i", 12) + b"12:34:56.78x", items=1, char=1),
        _datagram(2, b"\0" * 32, items=1, char=1, dgram=0x7F),  # a piece 127 of a message never completed
    ]
    src = open_source("mvn+udp://127.0.0.1:0")
    try:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for d in [*liars, *good]:
                tx.sendto(d, ("127.0.0.1", src.port))
        out, deadline = [], time.monotonic() + 5
        while src.decoder.counters["packets"] < len(liars) + len(good) and time.monotonic() < deadline:
            for p in src.read(0.1):
                out += src.decoder.feed(p)
        out += src.decoder.finish()
        c = src.decoder.counters
        assert (c["truncated"], c["bad_header"], c["bad_payload"], c["incomplete"]) == (3, 2, 5, 1)
        assert [f.sample_counter for f in _frames(out)[1]] == [0, 1, 2]
    finally:
        src.close()

    # seeded corruption: what breaks the layout is rejected, the rest decodes, nothing raises
    packets = mvn_packets(s0, clock="host") + mvn_packets(s1, clock="host")
    out, src, report = _receive("mvn+udp://127.0.0.1:0?characters=0,1", packets,
                                faults=Faults(seed=3, corrupt=0.08))  # fmt: skip
    corrupted = report.faults.corrupted
    played = merge(packets)  # the player's order: the FaultLog's indices
    # the ID's "MXTP", the payload size, and a pose's item count: always rejected when hit
    header_hits = [i for i, offs in corrupted.items()
                   if any(o < 4 or 22 <= o < 24 or (o == 11 and played[i].data[:6] == b"MXTP02") for o in offs)]
    c = src.decoder.counters
    rejected = c["truncated"] + c["bad_header"] + c["bad_payload"] + c["unsupported_type"] + c["other_character"]
    assert len(corrupted) > 20 and len(header_hits) > 0
    assert len(header_hits) <= rejected <= len(corrupted)
    bad_keys = {(_pose_key(played[i].data)[1:3]) for i in corrupted}
    frames = _frames(out)
    suit_of = {0: s0, 1: s1}
    clean = 0
    for ch, got in frames.items():
        assert ch in (0, 1)
        for f in got:
            if (ch, f.sample_counter) in bad_keys:
                continue
            clean += 1
            _check_frame(f, suit_of[ch], f.sample_counter, 0)
    intact = sum(1 for ch in (0, 1) for k in range(len(suit_of[ch])) if (ch, k) not in bad_keys)
    assert clean >= intact - 2 * len(corrupted)  # at most the counters a corrupt header could take over


def test_stale_character_and_segment_count_change(suits):
    s0, s1 = suits
    props = MVN_SEGMENTS + ("Prop1", "Prop2")
    extra_q = Rotation.random(2, random_state=9).as_quat()

    def with_props(k):
        f = s0.frame(k)
        if k < 60:
            return f
        return SuitFrame(0, f.sample_counter, f.time_code_ms, f.device_time_ns, f.host_time_ns, props,
                         np.vstack([f.orientations, extra_q]), np.vstack([f.positions, [[1, 1, 1], [2, 1, 0]]]))

    frames0 = [with_props(k) for k in range(len(s0))]
    packets = mvn_packets(frames0, clock="host") + mvn_packets(s1, clock="host")
    # character 1 goes silent from 0.15 s to 0.40 s of the 0.5 s play (real time)
    faults = Faults(outages=(Outage(0.15, 0.40, stream="mvn/1"),))
    out, src, report = _receive("mvn+udp://127.0.0.1:0?stale=0.1", packets, faults=faults, speed=1.0)
    events = src.decoder.pop_events()
    kinds = [(e.kind, e.entity) for e in events]
    assert ("stale", "mvn/1") in kinds and ("resumed", "mvn/1") in kinds
    assert kinds.index(("stale", "mvn/1")) < kinds.index(("resumed", "mvn/1"))
    stale = next(e for e in events if e.kind == "stale" and e.entity == "mvn/1")
    assert "MVN character 1 sent nothing for" in stale.message
    change = [e for e in events if e.kind == "segment-count-changed"]
    assert len(change) == 1 and change[0].entity == "mvn/0" and "now sends 25 segments (2 props" in change[0].message
    assert src.decoder.counters["segment_count_changes"] == 1
    got = _frames(out)[0]
    assert len(got) == len(s0) and got[59].segment_names == MVN_SEGMENTS and got[60].segment_names == props
    np.testing.assert_allclose(got[100].orientations[23:], extra_q, atol=2e-7)
    np.testing.assert_allclose(got[100].positions[23:], [[1, 1, 1], [2, 1, 0]], atol=1e-6)
    assert src.decoder.characters[0]["segments"] == 25
    silent = len(report.faults.outage)
    assert silent > 50 and len(_frames(out)[1]) < len(s1)
    # later, both have gone quiet: status says so, once
    later = now_ns() + 1_000_000_000
    status = src.decoder.status(later)
    assert not status["mvn/0"]["live"] and not status["mvn/1"]["live"] and status["mvn/0"]["segments"] == 25
    assert sorted((e.kind, e.entity) for e in src.decoder.pop_events()) == [("stale", "mvn/0"), ("stale", "mvn/1")]
    src.decoder.status(later + 1)
    assert src.decoder.pop_events() == []


def test_allow_list_rejects_another_sender_and_characters_filter(suits):
    s0, s1 = suits
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        stranger.bind(("127.0.0.2", 0))
        src = open_source("mvn+udp://127.0.0.1:0?allow=127.0.0.1&characters=1")
        try:
            with UdpPlayer(("127.0.0.1", src.port), speed=math.inf, sock=stranger) as p:
                p.add(mvn_packets([s0.frame(k) for k in range(5)], clock="host")).play()
            with UdpPlayer(("127.0.0.1", src.port), speed=math.inf) as p:
                p.add(mvn_packets([s0.frame(k) for k in range(4)], clock="host")
                      + mvn_packets([s1.frame(k) for k in range(6)], clock="host")).play()  # fmt: skip
            out, deadline = [], time.monotonic() + 5
            while src.decoder.counters["packets"] < 20 and time.monotonic() < deadline:
                for pkt in src.read(0.1):
                    out += src.decoder.feed(pkt)
            stats = src.stats()
        finally:
            src.close()
    finally:
        stranger.close()
    assert stats["rejected_senders"] == 10 and stats["datagrams"] == 20
    assert stats["other_character"] == 8 and stats["packets"] == 20
    frames = _frames(out)
    assert list(frames) == [1] and [f.sample_counter for f in frames[1]] == list(range(6))
    # the transport's event is the source's, the decoder's its own
    assert [(e.kind, e.entity) for e in src.pop_events()] == [("rejected-sender", "mvn")]
    assert [(e.kind, e.entity) for e in src.decoder.pop_events()] == [("other-character", "mvn")]


def test_url_parameters():
    dec = make_decoder("mvn+udp://0.0.0.0:9763?stale=2.5&characters=0,%203")
    assert isinstance(dec, MvnDecoder) and dec.stale_ns == 2_500_000_000 and dec.keep == {0, 3}
    assert make_decoder("mvn+udp://:9763").keep is None
    for url, match in [("mvn+udp://:1?stale=soon", "not a float"), ("mvn+udp://:1?stale=0", "positive"),
                       ("mvn+udp://:1?characters=0,300", "not an MVN character ID"),
                       ("mvn+udp://:1?characters=a", "not an MVN character ID"),
                       ("mvn+udp://:1?rate=5", "unknown mvn\\+udp:// parameter")]:  # fmt: skip
        with pytest.raises(SourceError, match=match):
            make_decoder(url)
    src = open_source("mvn+udp://127.0.0.1:0?rcvbuf=1048576")
    try:
        assert src.kind == "mvn" and src.port > 0 and MvnUdpSource.DEFAULT_PORT == 9763
        assert src.read(0.01) == []
    finally:
        src.close()


# ------------------------------------------------------------------------------------ hostile streams
_Q23, _P23 = np.tile([0.0, 0.0, 0.0, 1.0], (23, 1)), np.zeros((23, 3))
_PROP = MVN_SEGMENTS + ("Prop1",)


@functools.lru_cache(maxsize=16)
def _pose_template(char: int, names: tuple, max_datagram: int) -> tuple[bytes, ...]:
    n = len(names)
    return tuple(encode_pose(SuitFrame(char, 0, 0, 0, 0, names, np.tile([0.0, 0.0, 0.0, 1.0], (n, 1)),
                                       np.full((n, 3), 0.25)), max_datagram=max_datagram))  # fmt: skip


def _pose_dgrams(counter: int, *, tc: int | None = None, char: int = 0, names=MVN_SEGMENTS, max_datagram=1500):
    """Type-02 datagrams of one pose (counter and time code wrap to u32; time code 4 ms a counter)."""
    out = []
    for d in _pose_template(char, tuple(names), max_datagram):
        d = bytearray(d)
        struct.pack_into(">I", d, 6, counter % (1 << 32))
        struct.pack_into(">I", d, 12, (4 * counter if tc is None else tc) % (1 << 32))
        out.append(bytes(d))
    return out


def _feed_all(dec, datagrams, t0=0, step=1000):
    """Feed datagrams at host times ``t0 + k * step`` ns; returns the samples."""
    return [s for k, d in enumerate(datagrams) for s in dec.feed(RawPacket(t0 + k * step, d))]


def _no_guard_needed(dec):
    """The decoder's own code raised nothing (the Decoder base may count what would have escaped)."""
    assert dec.counters.get("decoder_errors", 0) == 0


def test_pending_pieces_are_bounded_at_every_piece():
    dec = MvnDecoder()
    big = b"\0" * 60_000  # not a whole pose: it stays pending
    flood = [_datagram(12, big, items=1, counter=c, dgram=i, char=c) for c in range(2) for i in range(100)]
    for k, d in enumerate(flood):
        dec.feed(RawPacket(k, d))
        assert dec._pending_bytes <= MAX_PENDING_BYTES and len(dec._pending) <= MAX_PENDING
        assert dec._pending_bytes == sum(p.nbytes for p in dec._pending.values())
    assert dec.counters["evicted"] >= 2  # each message alone outgrew the bound and was dropped
    # a real split message still goes through afterwards
    (got,) = _feed_all(dec, _pose_dgrams(7, max_datagram=24 + 32 * 8), t0=10**6)
    assert got.sample_counter == 7 and len(got.segment_names) == 23
    dec.finish()
    assert dec._pending_bytes == 0 and not dec._pending
    # what the Decoder guard calls after a fault: the waiting pieces go, counted
    evicted = dec.counters["evicted"]
    dec.feed(RawPacket(2 * 10**6, flood[0]))
    dec.recover()
    assert not dec._pending and dec._pending_bytes == 0 and dec.counters["evicted"] == evicted + 1
    _no_guard_needed(dec)


def test_one_stray_counter_neither_adds_loss_nor_moves_the_stream():
    dec = MvnDecoder()
    stream = [_pose_dgrams(c)[0] for c in range(100)]
    stream.insert(50, _pose_dgrams(100_000)[0])  # one datagram of another sender using the character ID
    out = _feed_all(dec, stream)
    assert [f.sample_counter for f in out] == list(range(100))
    c = dec.counters
    assert (c["lost"], c["counter_resets"], c["out_of_order"], c["out_of_sequence"]) == (0, 0, 0, 1)
    assert dec.characters[0]["out_of_sequence"] == 1 and dec.pop_events() == []
    _no_guard_needed(dec)


def test_counters_alternating_between_far_values_give_no_event_flood():
    dec = MvnDecoder()
    real = [_pose_dgrams(1000 + k)[0] for k in range(300)]
    stray = [_pose_dgrams(c)[0] for c in (5, 3_000_000_000, 77_777, 2_000_000_000)]
    stream = [d for k, r in enumerate(real) for d in (r, stray[k % 4])]
    out = _feed_all(dec, stream)
    assert [f.sample_counter for f in out] == [1000 + k for k in range(300)] and dec.finish() == []
    c = dec.counters
    assert (c["lost"], c["counter_resets"], c["out_of_sequence"], c["duplicate"]) == (0, 0, 300, 0)
    assert dec.pop_events() == []
    # bursts that do move the stream back and forth: every move counted, events at most one a second
    dec = MvnDecoder()
    a, b = [_pose_dgrams(k)[0] for k in range(400)], [_pose_dgrams(10**6 + k, tc=4 * k)[0] for k in range(400)]
    stream = [d for k in range(0, 400, 8) for d in a[k:k + 8] + b[k:k + 8]]
    out = _feed_all(dec, stream, step=1_000_000)  # 0.8 s of host time
    assert len(out) == 800 and dec.counters["counter_resets"] == 99 and dec.counters["lost"] == 0
    events = dec.pop_events()
    assert [e.kind for e in events] == ["counter-reset"]
    _no_guard_needed(dec)


def test_confirmed_jumps_restart_or_outage():
    # MVN restarts its counter: the new stream is taken once CONFIRM poses follow each other
    dec = MvnDecoder()
    out = _feed_all(dec, [_pose_dgrams(5000 + k)[0] for k in range(20)] + [_pose_dgrams(k)[0] for k in range(20)])
    assert [f.sample_counter % (1 << 32) for f in out] == [5000 + k for k in range(20)] + list(range(20))
    assert (dec.counters["counter_resets"], dec.counters["lost"], dec.counters["out_of_sequence"]) == (1, 0, 0)
    (ev,) = dec.pop_events()
    assert ev.kind == "counter-reset" and "went back by 5019" in ev.message
    # an outage of 500 samples (the time code went on with the counter): loss, no reset
    dec = MvnDecoder()
    out = _feed_all(dec, [_pose_dgrams(k)[0] for k in range(20)] + [_pose_dgrams(520 + k)[0] for k in range(20)])
    assert len(out) == 40 and dec.counters["lost"] == 500 and dec.counters["counter_resets"] == 0
    assert dec.pop_events() == []
    # a forward jump the time code cannot account for: a restart, not loss
    dec = MvnDecoder()
    jump = [_pose_dgrams(600_000 + k, tc=4 * (20 + k))[0] for k in range(20)]
    out = _feed_all(dec, [_pose_dgrams(k)[0] for k in range(20)] + jump)
    assert len(out) == 40 and dec.counters["lost"] == 0 and dec.counters["counter_resets"] == 1
    # a stream that ends while held: counted, not yielded
    dec = MvnDecoder()
    tail = [_pose_dgrams(9000 + k)[0] for k in range(CONFIRM - 1)]
    out = _feed_all(dec, [_pose_dgrams(k)[0] for k in range(20)] + tail)
    assert len(out) == 20 and dec.finish() == [] and dec.counters["out_of_sequence"] == CONFIRM - 1


def test_segment_count_change_is_clean_and_a_stray_layout_flips_nothing():
    dec = MvnDecoder()
    stream = [_pose_dgrams(k)[0] for k in range(30)]
    stream[10:10] = _pose_dgrams(10, names=_PROP)  # a stray 24-segment pose with an in-sequence counter
    for k in range(15, 25, 2):  # and more of them between the real ones
        stream.insert(k + 1, _pose_dgrams(k, names=_PROP)[0])
    stream += [_pose_dgrams(30 + k, names=_PROP)[0] for k in range(30)]  # a prop added for real
    out = _feed_all(dec, stream)
    assert [f.sample_counter for f in out] == list(range(60))
    assert [len(f.segment_names) for f in out] == [23] * 30 + [24] * 30
    assert all(f.segment_names == _PROP and f.positions.shape == (24, 3) for f in out[30:])
    (ev,) = dec.pop_events()
    assert ev.kind == "segment-count-changed" and "now sends 24 segments (1 props" in ev.message
    c = dec.counters
    assert (c["segment_count_changes"], c["out_of_sequence"], c["lost"], c["duplicate"]) == (1, 6, 0, 0)
    assert dec.characters[0]["segments"] == 24
    _no_guard_needed(dec)


# ------------------------------------------------------------------------------------ properties
_TYPES = (2, 2, 2, 12, 13, 20, 21, 22, 24, 25, 1, 23, 99)


@st.composite
def _mvn_datagrams(draw):
    """A datagram that is arbitrary bytes, or an MXTP header over arbitrary (or well-sized) items."""
    if draw(st.booleans()):
        return draw(st.binary(max_size=120))
    mtype = draw(st.sampled_from(_TYPES))
    items = draw(st.integers(0, 4))
    size = ITEM_SIZES.get(mtype, 0) * items
    payload = draw(st.binary(min_size=size, max_size=size)) if size and draw(st.booleans()) else \
        draw(st.binary(max_size=200))  # fmt: skip
    dgram = draw(st.sampled_from([0x80, 0x80, 0, 1, 2, 0x81, 0x82, 0x7F]) | st.integers(0, 255))
    return _datagram(mtype, payload, items=items, counter=draw(st.integers(0, 40) | st.integers(0, 2**32 - 1)),
                     dgram=dgram, tc=draw(st.integers(0, 2**32 - 1)), char=draw(st.integers(0, 2)),
                     props=draw(st.integers(0, 2)), fingers=draw(st.sampled_from([0, 0, 40])),
                     size=None if draw(st.integers(0, 9)) else draw(st.integers(0, 0xFFFF)))  # fmt: skip


def _check_bounded(dec, out, fed):
    """Never raised, every datagram and sample counted, state and events bounded."""
    _no_guard_needed(dec)
    c = dec.counters
    assert c["packets"] == len(fed) and c["bytes"] == sum(map(len, fed))
    assert c["samples"] == len(out) and c["frames"] == sum(isinstance(s, SuitFrame) for s in out)
    assert len({(f.character, f.sample_counter) for f in out if isinstance(f, SuitFrame)}) == c["frames"]
    assert 0 <= dec._pending_bytes <= MAX_PENDING_BYTES and len(dec._pending) <= MAX_PENDING
    assert dec._pending_bytes == sum(p.nbytes for p in dec._pending.values())
    for st_ in dec._chars.values():
        assert len(st_.held) <= MAX_CANDIDATES and all(len(h.items) < CONFIRM for h in st_.held)
        assert len(st_.seen) <= 2 * SEEN_WINDOW + 1
    # host times span under a second and under stale=: per character at most one event of each kind
    # (one per unsupported type and per ignored character)
    per_character = Counter((e.kind, e.entity) for e in dec.events if e.entity != "mvn")
    assert all(n == 1 for n in per_character.values()) and len(per_character) <= 2 * len(dec._chars)
    assert len(dec.events) - len(per_character) <= len(set(_TYPES)) + 256


@given(st.lists(_mvn_datagrams(), max_size=60))
def test_property_arbitrary_datagrams_never_raise_and_stay_bounded(datagrams):
    dec = MvnDecoder(characters=[0, 1])
    out = _feed_all(dec, datagrams)
    _check_bounded(dec, out, datagrams)
    out += dec.finish()
    assert not dec._pending and all(not st_.held for st_ in dec._chars.values())
    _check_bounded(dec, out, datagrams)


@st.composite
def _mutated_stream(draw):
    """Two characters' poses and time codes (split or whole), then dropped, duplicated, moved and
    byte-flipped datagrams."""
    base = draw(st.integers(0, 2**32 - 1))
    split = draw(st.sampled_from([1500, 24 + 32 * 8]))
    n = draw(st.integers(1, 16))
    grams = []
    for k in range(n):
        for char in (0, 1):
            f = SuitFrame(char, (base + k) % 2**32, (4 * (base + k)) % 2**32, 0, 0, MVN_SEGMENTS, _Q23, _P23)
            grams += encode_frame(f, max_datagram=split)
    ops = draw(st.lists(st.tuples(st.sampled_from(["drop", "dup", "move", "flip"]), st.integers(0, 10**6),
                                  st.integers(0, 10**6), st.integers(0, 255)), max_size=25))  # fmt: skip
    for op, i, j, v in ops:
        if not grams:
            break
        i %= len(grams)
        if op == "drop":
            del grams[i]
        elif op == "dup":
            grams.insert(j % (len(grams) + 1), grams[i])
        elif op == "move":
            grams.insert(j % len(grams), grams.pop(i))
        else:
            g = bytearray(grams[i])
            g[j % len(g)] = v
            grams[i] = bytes(g)
    return grams


@given(_mutated_stream())
def test_property_mutated_streams_never_raise_nor_yield_twice(datagrams):
    dec = MvnDecoder()
    out = _feed_all(dec, datagrams)
    out += dec.finish()
    _check_bounded(dec, out, datagrams)


@st.composite
def _hostile_pose_stream(draw):
    """One character's single-datagram poses from a u32 counter ``base``: drop bursts shorter than
    JUMP_GAP, duplicates, adjacent swaps, and isolated stray poses with far-off counters."""
    base = draw(st.integers(0, 2**32 - 1))
    n = draw(st.integers(2, 120))
    keep = [True] + draw(st.lists(st.booleans(), min_size=n - 1, max_size=n - 1))
    run = 0
    for k in range(n):
        run = run + 1 if not keep[k] else 0
        if run > JUMP_GAP - 4:
            keep[k], run = True, 0
    stream = [base + k for k in range(n) if keep[k]]
    for i in draw(st.lists(st.integers(0, 10**6), max_size=10)):
        if len(stream) > 1:
            i %= len(stream) - 1
            stream[i], stream[i + 1] = stream[i + 1], stream[i]
    for i, d in draw(st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 8)), max_size=10)):
        i %= len(stream)
        stream.insert(min(i + d, len(stream)), stream[i])  # a copy arrives a little later
    real = [(c, 4 * c) for c in stream]
    strays = draw(st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 10**5), st.integers(0, 2**32 - 1)),
                           max_size=8, unique_by=(lambda s: s[0] % len(real), lambda s: s[1])))  # fmt: skip
    for pos, far, tc in sorted(strays, reverse=True):  # never first: the first pose heard sets the stream
        real.insert(1 + pos % len(real), (base + 2048 + far * 4096, tc))  # far from the stream and each other
    return base, keep, real, len(strays)


@given(_hostile_pose_stream())
def test_property_strays_duplicates_and_reordering_add_up(case):
    base, keep, stream, n_strays = case
    dec = MvnDecoder()
    datagrams = [_pose_dgrams(c, tc=tc)[0] for c, tc in stream]
    out = _feed_all(dec, datagrams)
    out += dec.finish()
    _check_bounded(dec, out, datagrams)
    c = dec.counters
    received = {k for k, kept in enumerate(keep) if kept}
    got = [(f.sample_counter - base) % 2**32 for f in out]
    assert sorted(got) == sorted(received)  # every real pose once, no stray
    assert max(f.sample_counter for f in out) - min(f.sample_counter for f in out) == max(received) - min(received)
    assert c["frames"] + c["duplicate"] + c["out_of_sequence"] == len(datagrams)
    assert c["out_of_sequence"] == n_strays and c["counter_resets"] == 0
    assert c["lost"] == max(received) - min(received) + 1 - len(received)
    assert dec.events == []

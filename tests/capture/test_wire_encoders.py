"""Every encoder's bytes against the published layouts each wire module names (the MVN streaming
spec, the Xbus and MTi-600 CAN drivers, OpenHMD's VIVE HID report, our bridge datagram).

Each test reads the bytes back with its own ``struct`` formats and offsets, written here from
those layouts, never with a helper of the package.
"""

import math
import struct

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.samples import ImuSample, SuitFrame, TrackerSample
from dualhuman_builder.capture.wire.mti_can import encode_can
from dualhuman_builder.capture.wire.mvn import (
    ScalePoint, encode_frame, encode_meta, encode_pose, encode_scale, encode_time_code,
)  # fmt: skip
from dualhuman_builder.capture.wire.vive_udp import encode_tracker
from dualhuman_builder.capture.wire.xbus import SimulatedMti, encode_message, encode_mtdata2

SEGMENTS = (
    "Pelvis", "L5", "L3", "T12", "T8", "Neck", "Head", "RightShoulder", "RightUpperArm", "RightForeArm",
    "RightHand", "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand", "RightUpperLeg", "RightLowerLeg",
    "RightFoot", "RightToe", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToe",
)  # fmt: skip  -- the MVN spec's list, in ID order
# id, sample counter, datagram counter, items, time code, char, segments, props, fingers, reserved, payload size
MVN_HEADER = ">6sIBBIBBBBHH"
S2 = math.sqrt(0.5)


def _frame(character=0, counter=7, tc=1000, rot=None, seed=0) -> SuitFrame:
    rng = np.random.default_rng(seed)
    q = Rotation.random(23, random_state=seed).as_quat() if rot is None else np.tile(rot.as_quat(), (23, 1))
    return SuitFrame(character=character, sample_counter=counter, time_code_ms=tc, device_time_ns=tc * 10**6,
                     host_time_ns=tc * 10**6, segment_names=SEGMENTS, orientations=q,
                     positions=rng.uniform(-2, 2, (23, 3)))


def _header(d: bytes) -> dict:
    keys = ("id", "sample", "dgram", "items", "tc", "char", "segs", "props", "fingers", "reserved", "size")
    return dict(zip(keys, struct.unpack(MVN_HEADER, d[:24])))


def _zup(v):  # our Y-up (x, y, z) is MVN's Z-up (x, -z, y): up becomes +z
    return np.array([v[0], -v[2], v[1]])


# ------------------------------------------------------------------------------------------ MVN
def test_mvn_pose_header_items_and_byte_order():
    f = _frame(character=3, counter=0x01020304, tc=56789)
    (d,) = encode_pose(f)
    assert len(d) == 24 + 23 * 32 == 760
    h = _header(d)
    assert h == dict(id=b"MXTP02", sample=0x01020304, dgram=0x80, items=23, tc=56789, char=3, segs=23, props=0,
                     fingers=0, reserved=0, size=736)
    assert d[6:10] == b"\x01\x02\x03\x04" and d[22:24] == b"\x02\xe0"  # big-endian on the wire
    for k in range(23):
        seg_id, *pos, qw, qx, qy, qz = struct.unpack(">i7f", d[24 + 32 * k: 56 + 32 * k])
        assert seg_id == k + 1
        np.testing.assert_allclose(pos, _zup(f.positions[k]), atol=1e-6)  # metres, Z-up
        assert abs(qw * qw + qx * qx + qy * qy + qz * qz - 1) < 1e-6


def test_mvn_orientation_and_position_in_z_up():
    # A body facing our +X stands in MVN's null pose: forward +X, left -Z (our), up +Y.
    facing_x = Rotation.from_matrix(np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]))  # columns: forward, left, up
    f = _frame(rot=facing_x)
    f.positions[0] = [0.1, 1.0, -0.3]
    (d,) = encode_pose(f)
    _, *pos, qw, qx, qy, qz = struct.unpack(">i7f", d[24:56])
    np.testing.assert_allclose(pos, [0.1, 0.3, 1.0], atol=1e-6)  # 1 m above the floor -> z = 1
    np.testing.assert_allclose(np.abs([qw, qx, qy, qz]), [1, 0, 0, 0], atol=1e-6)
    # Facing our +Z (the identity body): its forward axis points to MVN's -Y, up stays +Z.
    facing_z = Rotation.from_matrix(np.array([[0.0, 1, 0], [0, 0, 1], [1, 0, 0]]))
    (d,) = encode_pose(_frame(rot=facing_z))
    _, *_, qw, qx, qy, qz = struct.unpack(">i7f", d[24:56])
    r = Rotation.from_quat([qx, qy, qz, qw])
    np.testing.assert_allclose(r.apply([1, 0, 0]), [0, -1, 0], atol=1e-6)
    np.testing.assert_allclose(r.apply([0, 0, 1]), [0, 0, 1], atol=1e-6)


def test_mvn_characters_share_a_port_differing_only_in_character_id():
    a, b = encode_pose(_frame(character=0))[0], encode_pose(_frame(character=1))[0]
    diff = [i for i in range(len(a)) if a[i] != b[i]]
    assert diff == [16] and (a[16], b[16]) == (0, 1)


def test_mvn_large_message_split_over_datagrams_and_reassembled():
    f = _frame(counter=99)
    (whole,) = encode_pose(f)
    pieces = encode_pose(f, max_datagram=24 + 5 * 32)
    heads = [_header(p) for p in pieces]
    assert [h["dgram"] for h in heads] == [0x00, 0x01, 0x02, 0x03, 0x84]
    assert [h["items"] for h in heads] == [5, 5, 5, 5, 3]
    assert all(h["sample"] == 99 and h["id"] == b"MXTP02" and h["size"] == len(p) - 24 for h, p in zip(heads, pieces))
    by_index = sorted(pieces, key=lambda p: p[10] & 0x7F)
    assert b"".join(p[24:] for p in by_index) == whole[24:]
    with pytest.raises(ValueError):
        encode_pose(f, max_datagram=24 + 31)  # cannot hold one item


def test_mvn_meta_time_code_and_frame():
    (m,) = encode_meta(2, name="alice", xmid="00B4A1F2", color="ff8800")
    h = _header(m)
    assert (h["id"], h["char"], h["dgram"], h["items"], h["segs"]) == (b"MXTP12", 2, 0x80, 1, 23)
    (n,) = struct.unpack(">i", m[24:28])
    assert n == len(m) - 28 == h["size"] - 4
    assert m[28:].decode() == "name:alice\nxmid:00B4A1F2\ncolor:FF8800\n"
    (t,) = encode_time_code(3_723_456, character=1, sample_counter=5)
    assert _header(t)["id"] == b"MXTP25" and _header(t)["tc"] == 3_723_456 and _header(t)["sample"] == 5
    assert t[24:] == b"\x00\x00\x00\x0c01:02:03.456"
    pose, tc = encode_frame(_frame(character=4, counter=11, tc=61_001))
    assert pose[:6] == b"MXTP02" and tc[:6] == b"MXTP25" and tc[16] == 4 and _header(tc)["sample"] == 11
    assert tc[28:] == b"00:01:01.001"


def test_mvn_scale_messages():
    origins = {name: (0.01 * i, 0.9 + 0.01 * i, -0.02 * i) for i, name in enumerate(SEGMENTS)}
    points = [ScalePoint(1 + i % 23, i, f"pt{i}", 1 << (i % 3), (0.0, 0.05 * i, 0.1)) for i in range(40)]
    msgs = encode_scale(5, origins, points, sample_counter=100, max_datagram=400)
    heads = [_header(d) for d in msgs]
    assert all(h["id"] == b"MXTP13" and h["char"] == 5 for h in heads)

    # the segment list (23 x (4+name+12) bytes) exceeds 400 bytes: pieces share sample counter 100
    first = [d for d, h in zip(msgs, heads) if h["sample"] == 100]
    assert len(first) > 1 and first[-1][10] == 0x80 | (len(first) - 1)
    assert [d[10] & 0x7F for d in first] == list(range(len(first)))
    assert sum(d[11] for d in first) == 23
    payload = b"".join(d[24:] for d in first)
    (s,) = struct.unpack_from(">i", payload, 0)
    off, got = 4, {}
    for _ in range(s):
        (ln,) = struct.unpack_from(">i", payload, off)
        name = payload[off + 4: off + 4 + ln].decode()
        got[name] = struct.unpack_from(">3f", payload, off + 4 + ln)
        off += 4 + ln + 12
    assert struct.unpack_from(">i", payload, off) == (0,) and off + 4 == len(payload)
    assert list(got) == list(SEGMENTS)
    for name, o in origins.items():
        np.testing.assert_allclose(got[name], _zup(o), atol=1e-6)

    # then point messages with S = 0, each in one datagram, consecutive sample counters
    rest = [(d, h) for d, h in zip(msgs, heads) if h["sample"] != 100]
    assert [h["sample"] for _, h in rest] == list(range(101, 101 + len(rest))) and len(rest) > 1
    seen = []
    for d, h in rest:
        assert h["dgram"] == 0x80 and len(d) <= 400
        p = d[24:]
        s, n = struct.unpack_from(">ii", p, 0)
        assert s == 0 and n == h["items"]
        off = 8
        for _ in range(n):
            seg, pid, ln = struct.unpack_from(">HHi", p, off)
            name = p[off + 8: off + 8 + ln].decode()
            flags, x, y, z = struct.unpack_from(">I3f", p, off + 8 + ln)
            seen.append((seg, pid, name, flags, (x, y, z)))
            off += 8 + ln + 16
        assert off == len(p)
    assert [(a, b, c, d) for a, b, c, d, _ in seen] == [(p.segment_id, p.point_id, p.name, p.flags) for p in points]
    np.testing.assert_allclose([v for *_, v in seen], [_zup(p.position) for p in points], atol=1e-6)


def test_mvn_rejects_bad_input():
    f = _frame()
    with pytest.raises(ValueError, match="unknown MVN segment"):
        encode_pose(SuitFrame(0, 0, 0, 0, 0, ("Tail",), np.array([[0, 0, 0, 1.0]]), np.zeros((1, 3))))
    bad = f.positions.copy()
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="non-finite"):
        encode_pose(SuitFrame(0, 0, 0, 0, 0, SEGMENTS, f.orientations, bad))
    with pytest.raises(ValueError, match="unit quaternion"):
        encode_pose(SuitFrame(0, 0, 0, 0, 0, SEGMENTS, f.orientations * 2, f.positions))
    with pytest.raises(ValueError, match="one byte"):
        encode_pose(_frame(character=256))


# ------------------------------------------------------------------------------------------ Xbus
def _frozen(v):  # simulators hand out read-only arrays
    a = np.array(v, dtype=np.float64)
    a.setflags(write=False)
    return a


def _imu(counter=70_000, t_ns=1_234_567_890, q=(0, 0, 0, 1.0), acc=(0.5, 9.80665, -1.25), gyr=(-0.1, 0.2, 3.0),
         mag=(0.3, -0.4, 0.9), status=0x00000403) -> ImuSample:
    return ImuSample(device="mti-1", counter=counter, device_time_ns=t_ns, host_time_ns=t_ns,
                     orientation=_frozen(q), acceleration=_frozen(acc), rate_of_turn=_frozen(gyr),
                     magnetic_field=_frozen(mag), status=status)


def _xbus_frames(stream: bytes) -> list[tuple[int, bytes]]:
    """(MID, data) of each frame, checking the preamble, bus ID, length and checksum."""
    out, i = [], 0
    while i < len(stream):
        assert stream[i: i + 2] == b"\xfa\xff"
        mid, n = stream[i + 2], stream[i + 3]
        head = 4
        if n == 0xFF:
            (n,) = struct.unpack(">H", stream[i + 4: i + 6])
            head = 6
        frame = stream[i: i + head + n + 1]
        assert sum(frame[1:]) % 256 == 0
        out.append((mid, frame[head: head + n]))
        i += head + n + 1
    return out


def test_xbus_frames_checksums_and_extended_length():
    assert encode_message(0x30) == bytes([0xFA, 0xFF, 0x30, 0x00, 0xD1])  # GoToConfig as documented
    assert encode_message(0x10) == bytes([0xFA, 0xFF, 0x10, 0x00, 0xF1])  # GoToMeasurement
    for n, extended in ((254, False), (255, True), (300, True), (2000, True)):
        data = bytes(np.random.default_rng(n).integers(0, 256, n, dtype=np.uint8))
        f = encode_message(0x36, data)
        if extended:
            assert f[3] == 0xFF and struct.unpack(">H", f[4:6]) == (n,) and f[6:-1] == data and len(f) == 7 + n
        else:
            assert f[3] == n and f[4:-1] == data and len(f) == 5 + n
        assert sum(f[1:]) % 256 == 0 and _xbus_frames(f) == [(0x36, data)]


def test_mtdata2_records():
    s = _imu()
    ((mid, data),) = _xbus_frames(encode_mtdata2(s))
    assert mid == 0x36
    recs, off = {}, 0
    while off < len(data):
        did, size = struct.unpack_from(">HB", data, off)
        recs[did] = data[off + 3: off + 3 + size]
        off += 3 + size
    assert list(recs) == [0x1020, 0x1060, 0x2010, 0x4020, 0x8020, 0xC020, 0xE020]
    assert all(did & 0x3 == 0 for did in recs)  # float32 precision
    assert struct.unpack(">H", recs[0x1020]) == (70_000 % 65536,)
    assert struct.unpack(">L", recs[0x1060]) == (12_346,)  # 1.2345679 s in 10 kHz ticks, rounded
    # identity in our Y-up world = +90 deg about X in the MTi's Z-up earth frame, (w, x, y, z)
    np.testing.assert_allclose(struct.unpack(">4f", recs[0x2010]), [S2, S2, 0, 0], atol=1e-7)
    assert struct.unpack(">3f", recs[0x4020]) == tuple(np.float32(s.acceleration).tolist())  # sensor frame
    assert struct.unpack(">3f", recs[0x8020]) == tuple(np.float32(s.rate_of_turn).tolist())
    assert struct.unpack(">3f", recs[0xC020]) == tuple(np.float32(s.magnetic_field).tolist())
    assert struct.unpack(">L", recs[0xE020]) == (0x403,)
    ((_, neg),) = _xbus_frames(encode_mtdata2(_imu(t_ns=-100_000), outputs=[0x1060]))
    assert struct.unpack(">HBL", neg) == (0x1060, 4, 0xFFFFFFFF)  # one tick before zero wraps like the counter
    ((_, only),) = _xbus_frames(encode_mtdata2(s, outputs=[0x2010, 0x1020]))
    assert struct.unpack_from(">HB", only, 0) == (0x2010, 16) and struct.unpack_from(">HB", only, 19) == (0x1020, 2)


def test_simulated_mti_answers_configuration_messages():
    mti = SimulatedMti(device_id=0x03601234)

    def msg(mid, data=b""):  # host-side frame, built here from the layout
        body = bytes([0xFF, mid, len(data)]) + data
        return b"\xfa" + body + bytes([-sum(body) & 0xFF])

    assert mti.mtdata2(_imu()) is not None  # measuring after power-on
    stream = b"\x00\x13garbage" + msg(0x30)
    reply = mti.answer(stream[:5]) + mti.answer(stream[5:9]) + mti.answer(stream[9:])  # any chunking
    assert _xbus_frames(reply) == [(0x31, b"")] and mti.mtdata2(_imu()) is None
    assert _xbus_frames(mti.answer(msg(0x00))) == [(0x01, b"\x03\x60\x12\x34")]
    cfg = struct.pack(">HHHH", 0x1020, 0xFFFF, 0x2010, 100)
    assert _xbus_frames(mti.answer(msg(0xC0, cfg))) == [(0xC1, cfg)]
    assert _xbus_frames(mti.answer(msg(0xC0))) == [(0xC1, cfg)]  # empty: current configuration
    assert _xbus_frames(mti.answer(msg(0xC0, struct.pack(">HH", 0x1234, 1)))) == [(0x42, b"\x21")]
    assert _xbus_frames(mti.answer(msg(0x7A))) == [(0x42, b"\x04")]  # unknown MID
    corrupt = bytearray(msg(0x10))
    corrupt[-1] ^= 0xFF
    assert mti.answer(bytes(corrupt)) == b"" and mti.bad_checksums == 1
    assert _xbus_frames(mti.answer(msg(0x3E) + msg(0x10))) == [(0x3F, b""), (0x11, b"")]
    ((_, data),) = _xbus_frames(mti.mtdata2(_imu()))
    assert struct.unpack_from(">HB", data, 0) == (0x1020, 2) and struct.unpack_from(">HB", data, 5) == (0x2010, 16)
    assert len(data) == 5 + 19
    assert _xbus_frames(mti.answer(msg(0xC0, cfg))) == [(0x42, b"\x04")]  # not in measurement state


# ------------------------------------------------------------------------------------------ CAN
def test_can_frames_ids_scales_signs_and_saturation():
    s = _imu(counter=65_537, t_ns=5_000_000_600, q=(0, 0, 0, 1.0), acc=(-1.5, 9.80665, 200.0),
             gyr=(-0.01, 0.5, -100.0), mag=(-0.25, 0.125, 40.0), status=0xA0000003)
    msgs = encode_can(s)
    assert [m.arbitration_id for m in msgs] == [0x05, 0x06, 0x11, 0x21, 0x32, 0x34, 0x35, 0x41]
    assert all(not m.is_extended_id for m in msgs)
    f = {m.arbitration_id: bytes(m.data) for m in msgs}
    assert [len(f[i]) for i in (0x05, 0x06, 0x11, 0x21, 0x32, 0x34, 0x35, 0x41)] == [4, 2, 4, 8, 6, 6, 6, 6]
    assert struct.unpack(">I", f[0x05]) == (5_000_001,)  # microseconds, rounded
    assert struct.unpack(">H", f[0x06]) == (1,)
    assert struct.unpack(">I", f[0x11]) == (0xA0000003,)
    assert struct.unpack(">4h", f[0x21]) == (23170, 23170, 0, 0)  # sqrt(1/2) * 2**15, Z-up (w, x, y, z)
    # -0.01 rad/s -> -5.12 -> -5 counts (two's complement); -100 rad/s saturates
    assert struct.unpack(">3h", f[0x32]) == (-5, 256, -32768)
    assert f[0x32][:2] == b"\xff\xfb"
    assert struct.unpack(">3h", f[0x34]) == (-384, 2511, 32767)  # 9.80665 * 256 = 2510.5 -> 2511; 200 m/s^2 saturates
    assert struct.unpack(">3h", f[0x41]) == (-256, 128, 32767)


def test_can_quaternion_of_one_saturates_and_free_acceleration():
    # -90 deg about our X is identity in Z-up: w = 1.0 -> 32768 does not fit, sent as 32767
    rest = _imu(q=Rotation.from_euler("x", -90, degrees=True).as_quat(), acc=(0.0, 0.0, 9.80665))
    f = {m.arbitration_id: bytes(m.data) for m in encode_can(rest)}
    assert struct.unpack(">4h", f[0x21]) == (32767, 0, 0, 0)
    assert struct.unpack(">3h", f[0x35]) == (0, 0, 0)  # at rest: no free acceleration
    # identity orientation in our world, accelerating 1 m/s^2 towards our +X and 2 m/s^2 up (+Y)
    moving = _imu(q=(0, 0, 0, 1.0), acc=(1.0, 9.80665 + 2.0, 0.0))
    f = {m.arbitration_id: bytes(m.data) for m in encode_can(moving)}
    assert struct.unpack(">3h", f[0x35]) == (256, 0, 512)  # Z-up earth frame: up is +z


# ------------------------------------------------------------------------------------------ VIVE
def test_tracker_datagram_fields():
    q = Rotation.from_euler("y", 30, degrees=True).as_quat()
    s = TrackerSample(serial="LHR-1A2B3C4D", valid=True, device_time_ns=123_456_789_012, host_time_ns=5,
                      position=np.array([0.25, 1.5, -2.0]), orientation=q, velocity=np.array([0.1, -0.2, 0.3]),
                      angular_velocity=np.array([1.0, 2.0, -3.0]))
    d = encode_tracker(s)
    assert len(d) == 128
    assert d[0:4] == b"DHVT" and d[4] == 1 and d[5] == 0b11 and d[6:8] == b"\0\0"
    assert d[8:40] == b"LHR-1A2B3C4D" + b"\0" * 20
    assert struct.unpack("<q", d[40:48]) == (123_456_789_012,) and d[40] == 123_456_789_012 & 0xFF  # little-endian
    assert struct.unpack("<3d", d[48:72]) == (0.25, 1.5, -2.0)
    assert struct.unpack("<4d", d[72:104]) == tuple(q)  # x, y, z, w
    assert struct.unpack("<3f", d[104:116]) == tuple(np.float32([0.1, -0.2, 0.3]).tolist())
    assert struct.unpack("<3f", d[116:128]) == (1.0, 2.0, -3.0)

    lost = TrackerSample(serial="T1", valid=False, device_time_ns=1, host_time_ns=1, position=np.full(3, np.nan),
                         orientation=np.full(4, np.nan), velocity=np.zeros(3), angular_velocity=np.zeros(3))
    d = encode_tracker(lost, connected=True)
    assert d[5] == 0b10 and struct.unpack("<3d4d", d[48:104]) == (0.0,) * 7
    early = TrackerSample("T1", True, -2_500_000, 0, np.zeros(3), q, np.zeros(3), np.zeros(3))
    assert struct.unpack("<q", encode_tracker(early)[40:48]) == (-2_500_000,)  # a clock offset may read < 0
    with pytest.raises(ValueError, match="serial"):
        encode_tracker(TrackerSample("X" * 33, True, 0, 0, np.zeros(3), q, np.zeros(3), np.zeros(3)))
    with pytest.raises(ValueError, match="non-finite"):
        encode_tracker(TrackerSample("T1", True, 0, 0, np.full(3, np.nan), q, np.zeros(3), np.zeros(3)))

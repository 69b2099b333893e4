"""VIVE tracker sources: ``vive+udp://`` over real UDP sockets on 127.0.0.1 fed by the simulated
devices' UdpPlayer, and ``vive+usb://`` — its HID report codec and decoder with encoded reports,
and the real pyusb/libusb path with no VIVE tracker plugged in."""

from __future__ import annotations

import math
import socket
import struct
import subprocess
import sys
import time
from collections import Counter

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.sources import RawPacket, SourceError, make_decoder, open_source
from dualhuman_builder.capture.vive_udp import (CONFIRM, ESTABLISHED, MAX_TRACKERS, SEQUENCE_NS, ViveUdpDecoder,
                                              ViveUdpSource)  # fmt: skip
from dualhuman_builder.capture.vive_usb import ViveUsbDecoder, ViveUsbSource
from dualhuman_builder.capture.samples import TrackerSample
from dualhuman_builder.capture.wire.vive_hid import (ACC_SCALE, GYRO_SCALE, HidImuSample, ViveHidError,
                                                     counts_from_si, decode_imu_report, encode_imu_report,
                                                     ticks_to_ns)  # fmt: skip
from dualhuman_builder.capture.wire.vive_udp import (MAGIC, TRACKER_DATAGRAM, ViveFormatError, decode_tracker,
                                                     encode_tracker)  # fmt: skip
from dualhuman_builder.sim.devices import Faults, UdpPlayer, corrupt_payload, tracker_packets
from dualhuman_builder.sim.kinematics import KinematicSpline
from dualhuman_builder.sim.trackers import TrackerErrorModel, default_sites, simulate_trackers
from dualhuman_builder.tracks import SkeletonTrack

SEGMENTS = ("Pelvis", "Head", "LeftHand", "RightHand", "LeftFoot", "RightFoot")
Q = np.array([0.0, 0.0, 0.0, 1.0])


def synthetic_spline(duration_s=0.6, fps=30.0) -> KinematicSpline:
    """Six segments of a body walking and turning (closed form), splined: a cheap ground truth."""
    t = np.arange(int(round(duration_s * fps)) + 1) / fps
    base = np.array([[0, 1.0, 0], [0, 1.6, 0], [0.7, 1.3, 0], [-0.7, 1.3, 0], [0.1, 0.1, 0], [-0.1, 0.1, 0]])
    yaw = Rotation.from_rotvec(np.outer(0.8 * t, [0, 1, 0]))
    pos = np.stack([yaw.apply(b) + np.outer(t, [0.4, 0, 0.1]) for b in base], 1)
    pos[:, 2:4, 1] += 0.1 * np.sin(4 * t)[:, None]
    quat = np.stack([(yaw * Rotation.from_rotvec([0, 0, 0.3 * k])).as_quat() for k in range(6)], 1)
    ns = np.round(t * 1e9).astype(np.int64)
    return KinematicSpline(SkeletonTrack(SEGMENTS, quat, pos, ns, ns, actor="synth", fps=fps))


SITES12 = {**default_sites("A"), **default_sites("B")}


def twelve_trackers(errors=None, seed=0, duration_s=0.6):
    return simulate_trackers(synthetic_spline(duration_s), SITES12, errors=errors or TrackerErrorModel.ideal(),
                             seed=seed)  # fmt: skip


def play_into(url, packets, *, faults=None, speed=10.0, sock=None):
    """Open ``url`` (port 0: ephemeral), play ``packets`` at it, decode everything that arrives."""
    src = open_source(url)
    player = UdpPlayer(("127.0.0.1", src.port), speed=speed, faults=faults, sock=sock).add(packets)
    samples = []
    try:
        player.start()
        while True:
            done = not player.running
            got = src.read(0.05)
            for p in got:
                samples += src.decoder.feed(p)
            if done and not got:
                break
        report = player.join()
        stats = src.stats()
    finally:
        src.close()
        player.close()
    assert stats.get("kernel_drops", 0) == 0
    return samples, report, stats, src.decoder


# ------------------------------------------------------------------------------------ vive+udp
def test_twelve_trackers_on_one_port_round_trip_exactly_with_tracking_loss():
    errors = TrackerErrorModel(loss_rate_per_min=600.0, loss_origin_fraction=0.5)
    tr = twelve_trackers(errors, seed=4)
    N, T = tr.valid.shape
    t_before = time.monotonic_ns()
    samples, report, stats, dec = play_into("vive+udp://127.0.0.1:0", tracker_packets(tr))
    t_after = time.monotonic_ns()
    status = dec.status(t_after)
    assert sorted(status) == sorted(f"vive/{s}" for s in SITES12)
    assert report.sent == N * T == len(samples) == stats["datagrams"] == stats["samples"]
    assert stats["packets"] == N * T and stats["bytes"] == N * T * 128
    got = {(s.serial, s.device_time_ns): s for s in samples}
    assert len(got) == N * T
    at_origin = ~tr.position.any(axis=-1)
    for i, serial in enumerate(tr.serials):
        for k in range(T):
            s = got[serial, int(tr.device_time_ns[k])]
            np.testing.assert_array_equal(s.position, tr.position[i, k])  # f64: bit for bit
            np.testing.assert_array_equal(s.orientation, tr.orientation[i, k])
            np.testing.assert_array_equal(s.velocity, tr.velocity[i, k].astype(np.float32))  # f32 on the wire
            np.testing.assert_array_equal(s.angular_velocity, tr.angular_velocity[i, k].astype(np.float32))
            assert s.valid == (tr.valid[i, k] and not at_origin[i, k])
    # tracking loss both ways, as the simulator made it
    assert stats["invalid_pose"] == (~tr.valid).sum() > 0
    assert stats["jumps_to_origin"] == (tr.valid & at_origin).sum() > 0
    assert not any(stats.get(k) for k in ("duplicate", "out_of_order", "bad_pose", "truncated", "disconnected"))
    host = [s.host_time_ns for s in samples]
    assert t_before <= host[0] and host[-1] <= t_after and all(np.diff(host) >= 0)
    assert all(v["live"] and v["rate_hz"] > 0 for v in status.values()), status
    for i, serial in enumerate(tr.serials):
        assert status[f"vive/{serial}"]["valid"] == bool(tr.valid[i, -1] and not at_origin[i, -1])


def test_loss_duplicates_and_reordering_match_the_players_fault_log():
    tr = twelve_trackers(seed=1, duration_s=0.4)
    packets = tracker_packets(tr)
    faults = Faults(seed=7, loss=0.05, duplicate=0.05, reorder=0.1, max_displacement=3)
    samples, report, stats, _ = play_into("vive+udp://127.0.0.1:0", packets, faults=faults)
    log = report.faults
    assert log.lost and log.duplicated and log.reordered
    sent_once = list(dict.fromkeys(log.sent))  # first emission of each packet, in sending order
    assert len(log.sent) - len(sent_once) == len(log.duplicated)
    merged = _player_packets(packets)
    # expected out-of-order samples: a later pose of the same tracker went before it
    newest: dict[str, int] = {}
    expected_ooo = 0
    for i in sent_once:
        stream = merged[i].stream
        if i < newest.get(stream, -1):
            expected_ooo += 1
        newest[stream] = max(newest.get(stream, -1), i)
    assert expected_ooo > 0
    assert stats["duplicate"] == len(log.duplicated)
    assert stats["out_of_order"] == expected_ooo
    assert stats["samples"] == len(samples) == len(sent_once)
    # exactly the packets sent came out, in the order they were first sent, none of the lost
    want = [decode_tracker(merged[i].data, 0) for i in sent_once]
    assert [(s.serial, s.device_time_ns) for s in samples] == [(w.serial, w.device_time_ns) for w in want]
    lost = {(decode_tracker(merged[i].data, 0).serial, decode_tracker(merged[i].data, 0).device_time_ns)
            for i in log.lost}  # fmt: skip
    assert not lost & {(s.serial, s.device_time_ns) for s in samples}


def _player_packets(packets):
    """The player's play order (its indices are the FaultLog's)."""
    player = UdpPlayer(("127.0.0.1", 9)).add(packets)
    player.close()
    return player.packets


def _expected_outcome(data: bytes) -> str:
    """What the datagram format says a (corrupted) datagram is, worked out from the layout."""
    if len(data) != 128:
        return "truncated" if len(data) < 128 else "bad_length"
    magic, version, flags, reserved, raw, _t, *v = TRACKER_DATAGRAM.unpack(data)
    if magic != MAGIC:
        return "bad_magic"
    if version != 1:
        return "bad_version"
    name = raw.rstrip(b"\0")
    if flags > 3 or reserved or not name or b"\0" in name or any(b > 127 for b in name):
        return "bad_field"
    if flags & 1 and (not np.all(np.isfinite(v)) or abs(math.hypot(*v[3:7]) - 1) > 1e-3):
        return "bad_pose"
    return "sample"


def test_corrupted_datagrams_are_rejected_by_field_or_decoded_as_sent():
    tr = simulate_trackers(synthetic_spline(1.0), {"LHR-0001": "Pelvis", "LHR-0002": "LeftHand"},
                           errors=TrackerErrorModel.ideal(), seed=2)  # fmt: skip
    packets = tracker_packets(tr)
    faults = Faults(seed=11, corrupt=0.4)
    samples, report, stats, _ = play_into("vive+udp://127.0.0.1:0", packets, faults=faults)
    merged = _player_packets(packets)
    log = report.faults
    assert len(log.corrupted) > 150
    offsets = Counter()
    outcomes = Counter()
    expected_samples = []
    for i in log.sent:
        data = merged[i].data
        if i in log.corrupted:
            data, off = corrupt_payload(data, seed=faults.seed, index=i, n_bytes=1)
            assert off == log.corrupted[i]
            offsets[off[0]] += 1
        outcome = _expected_outcome(data)
        outcomes[outcome] += 1
        if outcome == "sample":
            expected_samples.append(TRACKER_DATAGRAM.unpack(data))
    # a flipped byte of the device time that moves it further than SEQUENCE_NS is held, not yielded
    newest, in_sequence = {}, []
    for fields in expected_samples:
        serial, t = fields[4], fields[5]
        if serial in newest and abs(t - newest[serial]) > SEQUENCE_NS:
            continue
        newest[serial] = max(newest.get(serial, t), t)
        in_sequence.append(fields)
    assert 0 < len(expected_samples) - len(in_sequence) <= stats["out_of_sequence"] + CONFIRM
    # header faults by where the byte was flipped, independent of the decoder
    assert stats["bad_magic"] == sum(n for o, n in offsets.items() if o < 4) > 0
    assert stats["bad_version"] == offsets[4] > 0
    for kind in ("bad_magic", "bad_version", "bad_field", "bad_pose"):
        assert stats.get(kind, 0) == outcomes[kind], kind
    assert outcomes["bad_pose"] > 0 and outcomes["bad_field"] > 0
    assert stats["samples"] == len(samples) == len(in_sequence) and stats["packets"] == len(log.sent)
    # what was yielded is what the datagrams carried (the corrupted ones included), in order
    for s, (_, _, flags, _, raw, t, *v) in zip(samples, in_sequence):
        assert s.valid == (flags == 3)  # pose valid and device connected
        assert s.serial == raw.rstrip(b"\0").decode() and s.device_time_ns == t
        np.testing.assert_array_equal(np.concatenate([s.position, s.orientation, s.velocity, s.angular_velocity]), v)


def test_bad_datagrams_are_counted_and_decoding_goes_on():
    good = TrackerSample("LHR-GOOD", True, 1_000, 0, np.array([1.0, 2, 3]), Q, np.zeros(3), np.zeros(3))
    ok = encode_tracker(good)
    nan_pose = bytearray(ok)
    nan_pose[48:56] = struct.pack("<d", math.nan)
    long_quat = bytearray(ok)
    long_quat[96:104] = struct.pack("<d", 1.01)  # w
    bad_flags = bytearray(ok)
    bad_flags[5] |= 0x80
    bad_version = bytearray(ok)
    bad_version[4] = 2
    non_ascii = bytearray(ok)
    non_ascii[9] = 0xC3
    cases = [(b"", "truncated"), (ok[:100], "truncated"), (ok + b"\0" * 72, "bad_length"),
             (bytes(60000), "bad_length"), (b"GARBAGE!" * 16, "bad_magic"), (bytes(bad_version), "bad_version"),
             (bytes(bad_flags), "bad_field"), (bytes(non_ascii), "bad_field"), (bytes(nan_pose), "bad_pose"),
             (bytes(long_quat), "bad_pose")]  # fmt: skip
    for data, kind in cases:
        with pytest.raises(ViveFormatError) as e:
            decode_tracker(data, 0)
        assert e.value.counter == kind and isinstance(e.value, ValueError)
    assert "100 bytes, expected 128" in str(pytest.raises(ViveFormatError, decode_tracker, ok[:100], 0).value)
    assert "norm 1.01" in str(pytest.raises(ViveFormatError, decode_tracker, bytes(long_quat), 0).value)

    with open_source("vive+udp://127.0.0.1:0") as src, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        for data, _ in cases:
            tx.sendto(data, ("127.0.0.1", src.port))
        tx.sendto(ok, ("127.0.0.1", src.port))
        out, deadline = [], time.monotonic() + 2
        while src.decoder.counters["packets"] < len(cases) + 1 and time.monotonic() < deadline:
            for p in src.read(0.05):
                out += src.decoder.feed(p)
        stats = src.stats()
    assert stats["packets"] == stats["datagrams"] == len(cases) + 1
    assert {k: stats[k] for k in ("truncated", "bad_length", "bad_magic", "bad_version", "bad_field", "bad_pose")} == \
        {"truncated": 2, "bad_length": 2, "bad_magic": 1, "bad_version": 1, "bad_field": 2, "bad_pose": 2}
    assert len(out) == 1 and out[0].serial == "LHR-GOOD" and out[0].valid
    np.testing.assert_array_equal(out[0].position, [1, 2, 3])


def test_allow_rejects_a_sender_bound_to_another_address():
    tr = simulate_trackers(synthetic_spline(0.2), {"LHR-OK": "Head"}, errors=TrackerErrorModel.ideal())
    packets = tracker_packets(tr)
    stray = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stray.bind(("127.0.0.2", 0))
    src = open_source("vive+udp://127.0.0.1:0?allow=127.0.0.1")
    try:
        with UdpPlayer(("127.0.0.1", src.port), speed=math.inf, sock=stray) as p1:
            p1.add(packets).play()
        with UdpPlayer(("127.0.0.1", src.port), speed=math.inf) as p2:
            p2.add(packets).play()
        samples, deadline = [], time.monotonic() + 2
        while len(samples) < len(packets) and time.monotonic() < deadline:
            for p in src.read(0.05):
                samples += src.decoder.feed(p)
        stats = src.stats()
        events = src.pop_events()  # the transport's events are the source's
    finally:
        src.close()
        stray.close()
    assert stats["rejected_senders"] == len(packets) and stats["datagrams"] == len(packets) == len(samples)
    rejected = [e for e in events if e.kind == "rejected-sender"]
    assert len(rejected) == 1 and "127.0.0.2" in rejected[0].message


def _pose(serial, t_ns, *, valid=True, pos=(1.0, 1.0, 1.0), connected=True) -> bytes:
    s = TrackerSample(serial, valid, t_ns, 0, np.array(pos, float), Q, np.zeros(3), np.zeros(3))
    return encode_tracker(s, connected=connected)


def test_serials_filter_status_stale_resumed_and_flags():
    dec = make_decoder("vive+udp://:8051?serials=A,B&stale=0.2")
    assert isinstance(dec, ViveUdpDecoder)
    ms = 1_000_000
    feed = [(0, _pose("A", 0)), (4 * ms, _pose("C", 0)), (4 * ms, _pose("A", 4 * ms)), (8 * ms, _pose("C", 4 * ms)),
            (8 * ms, _pose("D", 0)), (8 * ms, _pose("A", 8 * ms)), (8 * ms, _pose("A", 8 * ms)),  # a duplicate
            (9 * ms, _pose("A", 2 * ms)),  # late: out of order, still yielded
            (12 * ms, _pose("B", 0, valid=False)), (16 * ms, _pose("B", 4 * ms, pos=(0, 0, 0)))]  # fmt: skip
    out = [s for t, d in feed for s in dec.feed(RawPacket(t, d))]
    assert [(s.serial, s.device_time_ns // ms, s.valid) for s in out] == \
        [("A", 0, True), ("A", 4, True), ("A", 8, True), ("A", 2, True), ("B", 0, False), ("B", 4, False)]
    c = dec.counters
    assert (c["other_serial"], c["duplicate"], c["out_of_order"], c["invalid_pose"], c["jumps_to_origin"]) == \
        (3, 1, 1, 1, 1)
    assert [(e.kind, e.entity) for e in dec.pop_events()] == [("other-serial", "vive/C"), ("other-serial", "vive/D")]
    st = dec.status(20 * ms)
    assert set(st) == {"vive/A", "vive/B"}
    assert st["vive/A"] == {"last_ns": 9 * ms, "live": True, "rate_hz": pytest.approx(3 / 0.009), "valid": True,
                            "connected": True}  # fmt: skip
    assert st["vive/B"]["valid"] is False and st["vive/B"]["rate_hz"] == pytest.approx(250.0)
    # A falls silent: stale once from status(), resumed on its next pose
    assert dec.status(300 * ms)["vive/A"]["live"] is False
    dec.status(400 * ms)
    assert [(e.kind, e.entity, e.host_time_ns) for e in dec.pop_events()] == \
        [("stale", "vive/A", 300 * ms), ("stale", "vive/B", 300 * ms)]
    dec.feed(RawPacket(500 * ms, _pose("A", 500 * ms)))
    # B's gap is first seen by feed: stale (at when it went stale) then resumed
    dec2 = ViveUdpDecoder(stale_s=0.1)
    for k in range(ESTABLISHED):  # events come for established trackers (serials= or ESTABLISHED samples)
        dec2.feed(RawPacket(k * ms, _pose("B", k * ms)))
    dec2.feed(RawPacket(250 * ms, _pose("B", 250 * ms)))
    assert [(e.kind, e.host_time_ns) for e in dec2.pop_events()] == [("stale", 107 * ms), ("resumed", 250 * ms)]
    ev = dec.pop_events()
    assert [(e.kind, e.entity) for e in ev] == [("resumed", "vive/A")] and "0.491 s" in ev[0].message
    assert dec.status(501 * ms)["vive/A"]["live"] is True
    # the device-connected flag: every sample with it clear is invalid; a change held for CONFIRM
    # samples is an event (a lone flipped flag is not)
    s = dec.feed(RawPacket(502 * ms, _pose("A", 502 * ms, connected=False)))
    assert s[0].valid is False and dec.counters["disconnected"] == 1
    dec.feed(RawPacket(503 * ms, _pose("A", 503 * ms)))
    assert dec.pop_events() == []
    for k in range(2 * CONFIRM):
        dec.feed(RawPacket((504 + k) * ms, _pose("A", (504 + k) * ms, connected=k >= CONFIRM)))
    assert [e.kind for e in dec.pop_events()] == ["disconnected", "connected"]
    assert dec.counters["disconnected"] == 1 + CONFIRM


def test_vive_udp_url_parameters():
    assert ViveUdpSource.PARAMS == ("allow", "rcvbuf", "stale", "serials") and ViveUdpSource.DEFAULT_PORT == 8051
    for url, words in [("vive+udp://:8051?stale=0", "stale"), ("vive+udp://:8051?stale=soon", "stale"),
                       ("vive+udp://:8051?serials=,", "serials"), ("vive+udp://:8051?bogus=1", "bogus")]:  # fmt: skip
        with pytest.raises(SourceError, match=words):
            make_decoder(url)
    with open_source("vive+udp://127.0.0.1:0?serials=X") as src:
        assert src.kind == "vive" and src.decoder.serials == {"X"} and src.port > 0


# ------------------------------------------------------------------------------------ vive+usb
def test_hid_report_layout_and_round_trip():
    slots = [HidImuSample((1, -2, 4096), (-32768, 32767, 0), 0xFFFFFFFF, 255),
             HidImuSample((0, 0, 0), (1, 1, 1), 7, 0), HidImuSample((5, 6, 7), (8, 9, 10), 2**31, 1)]  # fmt: skip
    data = encode_imu_report(slots)
    assert len(data) == 52 and data[0] == 0x20
    assert data[1:3] == (1).to_bytes(2, "little") and data[5:7] == (4096).to_bytes(2, "little")
    assert data[13:17] == b"\xff\xff\xff\xff" and data[17] == 255 and data[18 + 16] == 0 and data[51] == 1
    assert decode_imu_report(data) == tuple(slots)
    acc, gyro = counts_from_si([0.0, 0.0, 9.80665], [0.0, math.radians(1000.0), -100.0])
    assert acc == (0, 0, 4096) and gyro == (0, 32768 - 1, -32768)  # 1000 deg/s = 32768 counts: clipped
    for bad, kind in [(data[:51], "truncated"), (b"", "truncated"), (data + bytes(12), "bad_length"),
                      (b"\x21" + data[1:], "unknown_id")]:  # fmt: skip
        with pytest.raises(ViveHidError) as e:
            decode_imu_report(bad)
        assert e.value.counter == kind
    with pytest.raises(ValueError, match="3 samples"):
        encode_imu_report(slots[:2])
    with pytest.raises(ValueError, match="int16"):
        encode_imu_report([HidImuSample((40000, 0, 0), (0, 0, 0), 0, 0)] * 3)


def _device_reports(n, t0_ticks, seq0, period=48_000):
    """The reports a tracker sends after each of ``n`` IMU samples: slot k % 3 holds sample k
    (a ring of the latest three), so each sample is sent three times, slots not in time order."""
    rng = np.random.default_rng(0)
    acc = rng.integers(-5000, 5000, (n, 3))
    gyro = rng.integers(-3000, 3000, (n, 3))
    ticks = [(t0_ticks + k * period) % 2**32 for k in range(n)]
    raw = [HidImuSample(tuple(map(int, acc[k])), tuple(map(int, gyro[k])), ticks[k], (seq0 + k) % 256)
           for k in range(n)]  # fmt: skip
    reports = []
    for j in range(2, n):
        ring = [None] * 3
        for k in range(j - 2, j + 1):
            ring[k % 3] = raw[k]
        reports.append((j, encode_imu_report(ring)))
    return raw, acc, gyro, reports


def test_usb_decoder_unwraps_ticks_drops_repeats_and_counts_lost_samples():
    n, t0 = 2600, 2**32 - 100 * 48_000  # the u32 tick counter wraps at sample 100, seq at 6
    raw, acc, gyro, reports = _device_reports(n, t0, seq0=250)
    dropped = set(range(150, 157)) | set(range(200, 502)) | set(range(800, 2302))  # 5, 300 and 1500 samples lost
    dec = ViveUsbDecoder("LHR-USB1")
    out, fed = [], 0
    for j, data in reports:
        if j in dropped:
            continue
        for d in ([data, data] if j == 1000 else [data]) + ([b"\x23" + bytes(40), data[:30]] if j == 40 else []):
            out += dec.feed(RawPacket(10_000 + j, d))
            fed += 1
    got = [k for k in range(n) if any(j not in dropped for j in (k, k + 1, k + 2) if 2 <= j < n)]
    assert len(out) == len(got) == n - 5 - 300 - 1500
    assert [s.counter for s in out] == [raw[k].seq for k in got]
    want_ns = [ticks_to_ns(t0 + k * 48_000) for k in got]
    assert [s.device_time_ns for s in out] == want_ns  # unwrapped across the u32 wrap
    assert np.all(np.diff(want_ns) > 0) and want_ns[120] - want_ns[0] == 120_000_000  # 48 MHz -> 1 kHz exactly
    np.testing.assert_array_equal(np.array([s.acceleration for s in out]), acc[got] * ACC_SCALE)
    np.testing.assert_array_equal(np.array([s.rate_of_turn for s in out]), gyro[got] * GYRO_SCALE)
    assert all(np.isnan(s.orientation).all() and np.isnan(s.magnetic_field).all() for s in out)
    assert {s.device for s in out} == {"LHR-USB1"} and out[5].host_time_ns == 10_000 + 5
    c = dec.counters
    assert c["lost"] == 5 + 300 + 1500 and c["samples"] == len(out) and c["packets"] == fed
    assert c["duplicate"] == 3 * (fed - 2) - len(out)  # every slot of every IMU report, once new
    assert c["unknown_id"] == 1 and c["truncated"] == 1
    events = dec.pop_events()
    assert [e.kind for e in events] == ["unknown-report", "gap"] and "1500 lost" in events[1].message


def _valve_device_present() -> bool:
    import usb.core

    try:
        return bool(list(usb.core.find(find_all=True, idVendor=0x28DE)))
    except usb.core.NoBackendError:
        return False


@pytest.mark.skipif(_valve_device_present(), reason="a Valve USB device is plugged in: the absence error cannot occur")
def test_usb_source_without_a_device_says_what_was_looked_for():
    with pytest.raises(SourceError) as e:
        open_source("vive+usb://")
    msg = str(e.value)
    assert "no Valve USB device found" in msg and "vendor 0x28de" in msg
    assert all(p in msg for p in ("0x2022 VIVE Tracker", "0x2300 VIVE Tracker v2", "0x2101 Watchman dongle"))
    t = time.monotonic()
    with pytest.raises(SourceError, match="serial 'LHR-00000000' found within 0.3 s"):
        ViveUsbSource("vive+usb://?serial=LHR-00000000&timeout=0.3")
    assert time.monotonic() - t >= 0.3


def test_usb_url_parameters():
    for url, words in [("vive+usb://?timeout=soon", "timeout"), ("vive+usb://?port=1", "port"),
                       ("vive+usb://host/x", "no host or path"), ("vive+usb://?timeout=-1", "timeout")]:  # fmt: skip
        with pytest.raises(SourceError, match=words):
            open_source(url)
    assert ViveUsbSource.make_decoder("vive+usb://?serial=LHR-9").device == "LHR-9"
    assert make_decoder("vive+usb://").device == "vive-usb"


def test_usb_source_without_libusb_says_how_to_install_it():
    # a fresh interpreter, so that pyusb has not loaded libusb yet; the library lookup finds nothing
    code = ("from dualhuman_builder.capture.vive_usb import ViveUsbSource\n"
            "try:\n    ViveUsbSource('vive+usb://', find_library=lambda name: None)\n"
            "except Exception as e:\n    print(type(e).__name__, e)\n")  # fmt: skip
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert r.stdout.startswith("SourceError cannot open 'vive+usb://': pyusb finds no libusb-1.0 backend")
    assert "(fix: apt-get install libusb-1.0-0)" in r.stdout


# ------------------------------------------------------------------------------------ hostile streams
def _no_guard_needed(dec):
    """The decoder's own code raised nothing (the Decoder base may count what would have escaped)."""
    assert dec.counters.get("decoder_errors", 0) == 0


def test_invented_serials_cannot_lock_real_trackers_out():
    ms = 1_000_000
    dec = ViveUdpDecoder()
    invented = [RawPacket(k, _pose(f"FAKE-{k:05d}", k)) for k in range(3 * MAX_TRACKERS)]
    assert len([s for p in invented for s in dec.feed(p)]) == 3 * MAX_TRACKERS  # unlisted serials are kept...
    real = [s for k in range(20) for s in dec.feed(RawPacket(ms + k * 4 * ms, _pose("LHR-REAL", k * 4 * ms)))]
    assert [s.device_time_ns for s in real] == [k * 4 * ms for k in range(20)]  # ...but make room for a live one
    c = dec.counters
    assert c["too_many_trackers"] == 0 and c["evicted_trackers"] == 2 * MAX_TRACKERS + 1
    assert len(dec.trackers) == MAX_TRACKERS and "LHR-REAL" in dec.trackers
    (full,) = dec.pop_events()
    assert full.kind == "tracker-table-full" and full.entity == "vive" and "serials=" in full.message
    # a table of established trackers that are all sending: a new serial is dropped, counted, no new event
    dec = ViveUdpDecoder()
    for k in range(ESTABLISHED):
        for i in range(MAX_TRACKERS):
            dec.feed(RawPacket(k * ms, _pose(f"T{i:03d}", k * ms)))
    assert dec.feed(RawPacket(9 * ms, _pose("LATE", 9 * ms))) == []
    assert dec.feed(RawPacket(10 * ms, _pose("LATE", 10 * ms))) == []
    assert dec.counters["too_many_trackers"] == 2 and [e.kind for e in dec.pop_events()] == ["tracker-table-full"]
    # once one falls silent for longer than stale_s, the newcomer takes its place
    for i in range(1, MAX_TRACKERS):
        dec.feed(RawPacket(400 * ms, _pose(f"T{i:03d}", 400 * ms)))
    (got,) = dec.feed(RawPacket(600 * ms, _pose("LATE", 600 * ms)))
    assert got.serial == "LATE" and "T000" not in dec.trackers and dec.counters["evicted_trackers"] == 1
    _no_guard_needed(dec)


def test_a_stray_device_time_is_held_and_the_stream_stays_in_order():
    ms = 1_000_000
    dec = ViveUdpDecoder()
    t0 = 10**10  # device ns
    feed = [(k * 4 * ms, _pose("LHR-A", t0 + k * 4 * ms)) for k in range(40)]
    feed.insert(20, (80 * ms, _pose("LHR-A", 10**15)))  # one datagram with a far-off device time
    out = [s for t, d in feed for s in dec.feed(RawPacket(t, d))]
    assert [s.device_time_ns for s in out] == [t0 + k * 4 * ms for k in range(40)]
    c = dec.counters
    assert (c["out_of_order"], c["out_of_sequence"], c["clock_resets"], c["duplicate"]) == (0, 1, 0, 0)
    # the bridge restarts its clock: taken after CONFIRM samples, one event
    back = [s for k in range(10) for s in dec.feed(RawPacket((200 + 4 * k) * ms, _pose("LHR-A", k * 4 * ms + 1)))]
    assert len(back) == 10 and dec.counters["clock_resets"] == 1 and dec.counters["out_of_order"] == 0
    assert [e.kind for e in dec.pop_events()] == ["clock-reset"]
    # a tracker that pauses (device time goes on with the host's): no event, nothing lost
    later = [s for k in range(10)
             for s in dec.feed(RawPacket((1300 + 4 * k) * ms, _pose("LHR-A", (1100 + 4 * k) * ms)))]  # fmt: skip
    assert len(later) == 10 and dec.counters["clock_resets"] == 1
    assert [e.kind for e in dec.pop_events()] == ["stale", "resumed"]
    _no_guard_needed(dec)


def test_flags_flipping_every_datagram_give_no_event_flood():
    ms = 1_000_000
    dec = ViveUdpDecoder(serials=["LHR-A"])
    out = [s for k in range(400) for s in dec.feed(RawPacket(k * ms, _pose("LHR-A", k * ms, connected=k % 2 == 0)))]
    assert len(out) == 400 and sum(not s.valid for s in out) == 200 == dec.counters["disconnected"]
    assert dec.pop_events() == []
    # changes that hold for CONFIRM samples but come faster than one a second: events rate-limited
    out = [s for k in range(400) for s in
           dec.feed(RawPacket((400 + k) * ms, _pose("LHR-A", (400 + k) * ms, connected=(k // CONFIRM) % 2 == 1)))]
    kinds = [e.kind for e in dec.pop_events()]
    assert kinds == ["disconnected", "connected"]
    _no_guard_needed(dec)


# ------------------------------------------------------------------------------------ properties
_REJECTED = ("truncated", "bad_length", "bad_magic", "bad_version", "bad_field", "bad_pose")


@st.composite
def _vive_datagrams(draw):
    """Arbitrary bytes, or the datagram layout with arbitrary fields (few serials, any flags and values)."""
    if draw(st.integers(0, 3)) == 0:
        return draw(st.binary(max_size=140))
    serial = draw(st.sampled_from([b"A", b"B", b"LHR-1", b"", b"A\0B", b"\xc3"]) | st.binary(min_size=1, max_size=32))
    values = draw(st.lists(st.floats(allow_nan=True, allow_infinity=True), min_size=13, max_size=13))
    if draw(st.booleans()):
        values[3:7] = [0.0, 0.0, 0.0, 1.0]
    return TRACKER_DATAGRAM.pack(draw(st.sampled_from([MAGIC, MAGIC, b"DHVX"])), draw(st.sampled_from([1, 1, 2])),
                                 draw(st.sampled_from([3, 3, 1, 2, 0, 7])), draw(st.sampled_from([0, 0, 1])),
                                 serial, draw(st.integers(0, 40) | st.integers(-(2**63), 2**63 - 1)),
                                 *values[:7], *[float(np.float32(v)) if math.isfinite(v) and abs(v) < 1e38 else 0.0
                                                for v in values[7:]])  # fmt: skip


def _check_vive(dec, out, fed):
    """Never raised; after finish every datagram is in exactly one counter; state and events bounded."""
    _no_guard_needed(dec)
    c = dec.counters
    assert c["packets"] == len(fed) and c["bytes"] == sum(map(len, fed)) and c["samples"] == len(out)
    assert c["packets"] == sum(c[k] for k in _REJECTED) + c["other_serial"] + c["too_many_trackers"] + \
        c["duplicate"] + c["out_of_sequence"] + c["samples"]  # fmt: skip
    assert len({(s.serial, s.device_time_ns) for s in out}) == len(out)  # never yielded twice
    assert len(dec.trackers) <= MAX_TRACKERS and len(dec._ignored) <= MAX_TRACKERS
    for tr in dec.trackers.values():
        assert not tr.held and len(tr.recent) <= 64
    # host times span under stale= and a second: at most one event of each kind per tracker
    per_tracker = Counter((e.kind, e.entity) for e in dec.events)
    assert all(n == 1 for n in per_tracker.values())
    assert len(per_tracker) <= 3 * len(dec.trackers) + len(dec._ignored) + 1


@given(st.lists(_vive_datagrams(), max_size=60), st.booleans())
def test_property_arbitrary_datagrams_never_raise_and_add_up(datagrams, listed):
    dec = ViveUdpDecoder(serials=["A", "LHR-1"] if listed else None)
    out = [s for k, d in enumerate(datagrams) for s in dec.feed(RawPacket(k * 1000, d))]
    out += dec.finish()
    _check_vive(dec, out, datagrams)


@st.composite
def _hostile_tracker_stream(draw):
    """Three trackers at 4 ms: dropped, duplicated (a little later), swapped and byte-flipped
    datagrams, and isolated strays with far-off device times."""
    n = draw(st.integers(1, 30))
    t0 = draw(st.integers(0, 2**62))
    stream = [(f"LHR-{i}", t0 + k * 4_000_000) for k in range(n) for i in range(3)]
    for i in draw(st.lists(st.integers(0, 10**6), max_size=10)):
        if stream:
            del stream[i % len(stream)]
    for i in draw(st.lists(st.integers(0, 10**6), max_size=10)):
        if len(stream) > 1:
            i %= len(stream) - 1
            stream[i], stream[i + 1] = stream[i + 1], stream[i]
    for i, d in draw(st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 8)), max_size=10)):
        if stream:
            i %= len(stream)
            stream.insert(min(i + d, len(stream)), stream[i])
    real = list(stream)
    strays = draw(st.lists(st.tuples(st.integers(0, 10**6), st.integers(0, 2), st.integers(1, 10**6)), max_size=6,
                           unique_by=(lambda s: s[0] % max(len(real), 1), lambda s: s[2])))  # fmt: skip
    mixed = list(real)
    for pos, i, far in sorted(strays, reverse=True):  # after the tracker's first sample: the first sets the stream
        first = next((k for k, (s, _) in enumerate(mixed) if s == f"LHR-{i}"), None)
        if first is not None:
            mixed.insert(first + 1 + pos % (len(mixed) - first), (f"LHR-{i}", (t0 + far * 10**9 * 7) % 2**62))
    return real, mixed


@given(_hostile_tracker_stream())
def test_property_strays_duplicates_and_reordering_add_up(case):
    real, mixed = case
    dec = ViveUdpDecoder()
    datagrams = [_pose(s, t) for s, t in mixed]
    out = [s for k, d in enumerate(datagrams) for s in dec.feed(RawPacket(k * 1000, d))]
    out += dec.finish()
    _check_vive(dec, out, datagrams)
    c = dec.counters
    assert sorted((s.serial, s.device_time_ns) for s in out) == sorted(set(real))  # every real pose once, no stray
    assert c["duplicate"] == len(real) - len(set(real)) and c["out_of_sequence"] == len(mixed) - len(real)
    assert c["clock_resets"] == 0 and dec.events == []

"""Simulated device players on real transports: UDP loopback, loop:// and a pty, python-can's
virtual bus; pacing, the Xbus configuration dialogue, and seeded, recorded faults."""

import math
import os
import select
import socket
import struct
import threading
import time
import uuid
from dataclasses import replace

import can
import numpy as np
import serial
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.samples import ImuSample, SuitFrame, TrackerSample
from dualhuman_builder.sim.devices import (
    CanPlayer, Faults, Outage, Packet, PtyMaster, SerialPlayer, UdpPlayer, mvn_packets, plan_faults, tracker_packets,
)  # fmt: skip

SEGMENTS = (
    "Pelvis", "L5", "L3", "T12", "T8", "Neck", "Head", "RightShoulder", "RightUpperArm", "RightForeArm",
    "RightHand", "LeftShoulder", "LeftUpperArm", "LeftForeArm", "LeftHand", "RightUpperLeg", "RightLowerLeg",
    "RightFoot", "RightToe", "LeftUpperLeg", "LeftLowerLeg", "LeftFoot", "LeftToe",
)  # fmt: skip


def _frames(character, n, hz=240.0, t0_ns=0):
    q = Rotation.random(23, random_state=character).as_quat()
    return [SuitFrame(character, k, round(k * 1000 / hz), t0_ns + round(k * 1e9 / hz), t0_ns + round(k * 1e9 / hz),
                      SEGMENTS, q, np.full((23, 3), 0.01 * k)) for k in range(n)]


def _trackers(serial_no, n, hz=250.0, offset_ns=0):
    return [TrackerSample(serial_no, True, offset_ns + round(k * 1e9 / hz), round(k * 1e9 / hz),
                          np.array([0.0, 1.0, 0.001 * k]), np.array([0, 0, 0, 1.0]), np.zeros(3), np.zeros(3))
            for k in range(n)]


def _imus(n, hz=400.0):
    return [ImuSample("mti-1", k, round(k * 1e9 / hz), round(k * 1e9 / hz), np.array([0, 0, 0, 1.0]),
                      np.array([0.0, 9.80665, 0.01 * k]), np.array([0.1, 0.0, 0.0]), np.array([0.3, 0.0, 0.4]))
            for k in range(n)]


class UdpReceiver:
    """Collects datagrams on 127.0.0.1 in a thread, with their arrival times."""

    def __init__(self):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 22)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(0.2)
        self.address = self.sock.getsockname()
        self.got: list[tuple[float, bytes]] = []
        self._done = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        while not self._done.is_set():
            try:
                data, _ = self.sock.recvfrom(65535)
            except socket.timeout:
                continue
            self.got.append((time.perf_counter(), data))

    def wait_for(self, n, timeout=10.0):
        deadline = time.monotonic() + timeout
        while len(self.got) < n and time.monotonic() < deadline:
            time.sleep(0.005)
        time.sleep(0.05)  # anything extra (there must be none) would arrive now
        self._done.set()
        self._thread.join()
        self.sock.close()
        return [d for _, d in self.got]


# ------------------------------------------------------------------------------------------ transports
def test_udp_two_suits_and_trackers_merged_onto_one_port():
    suits = mvn_packets(_frames(0, 30)) + mvn_packets(_frames(1, 30))
    trackers = tracker_packets(_trackers("LHR-A", 30)) + tracker_packets(_trackers("LHR-B", 30))
    rx = UdpReceiver()
    with UdpPlayer(rx.address, speed=20.0) as player:
        player.add(suits).add(trackers)
        expected = [p.data for p in player.packets]
        report = player.start().join()
    got = rx.wait_for(len(expected))
    assert got == expected  # every datagram intact, in time order
    assert report.completed and report.sent == 180 and report.bytes_sent == sum(map(len, expected))
    assert report.per_stream == {"mvn/0": 60, "mvn/1": 60, "vive/LHR-A": 30, "vive/LHR-B": 30}
    times = [p.time_ns for p in player.packets]
    assert times == sorted(times)
    chars = [d[16] for d in got if d[:4] == b"MXTP"]
    assert chars.count(0) == chars.count(1) == 60 and 0 < chars.index(1) < 4  # interleaved, not one suit then the other


def test_speed_plays_n_times_faster_and_never_early():
    span_s = 0.4
    packets = [Packet(round(k * span_s * 1e9 / 40), b"%03d" % k, "s") for k in range(41)]
    elapsed = {}
    for speed in (2.0, 20.0):
        rx = UdpReceiver()
        with UdpPlayer(rx.address, speed=speed) as player:
            player.add(packets)
            start = time.perf_counter()
            report = player.play()
        rx.wait_for(41)
        assert [d for _, d in rx.got] == [p.data for p in packets]
        # no packet leaves before its scheduled time (a little slack for clock reads)
        for (t, _), p in zip(rx.got, packets):
            assert t - start >= p.time_ns / 1e9 / speed - 0.002
        elapsed[speed] = report.elapsed_s
        assert report.elapsed_s >= span_s / speed * 0.95
    assert elapsed[20.0] < elapsed[2.0] / 3  # 10x faster, with generous tolerance
    fast = UdpPlayer(("127.0.0.1", 9), speed=math.inf).add(packets)  # as fast as possible: discard port
    assert fast.play().sent == 41 and fast.report.elapsed_s < span_s
    fast.close()


def test_players_sharing_a_clock_keep_their_streams_aligned_when_one_thread_starts_late():
    """Two devices of one studio: the second player's thread starts 150 ms late (a loaded
    machine); with a shared clock its overdue packets go at once and the rest keep the common
    schedule, so its stream is not shifted against the first one's."""
    span_ns = 600_000_000
    first = [Packet(k * span_ns // 30, b"a%02d" % k, "a") for k in range(31)]
    second = [Packet(5_000_000 + k * span_ns // 30, b"b%02d" % k, "b") for k in range(31)]
    rx = UdpReceiver()
    with UdpPlayer(rx.address, speed=1.0) as pa, UdpPlayer(rx.address, speed=1.0) as pb:
        pa.add(first)
        pb.add(second)
        UdpPlayer.share_clock([pa, pb], lead_s=0.02)
        start = pa.epoch[0]
        assert pb.epoch == pa.epoch and pa.epoch[1] == 0  # the earliest packet of either is time 0
        pa.start()
        time.sleep(0.15)
        pb.start()
        pa.join(), pb.join()
    rx.wait_for(62)
    arrival = {d: t - start for t, d in rx.got}
    late = [arrival[p.data] - p.time_ns / 1e9 for p in second]
    # packets due before the late start left in a burst right after it; later ones on schedule
    assert all(x >= -0.002 for x in late)
    on_time = [x for p, x in zip(second, late) if p.time_ns > 0.2e9]
    assert len(on_time) >= 15 and max(on_time) < 0.02
    assert max(late) > 0.1  # the burst was late
    assert max(arrival[p.data] - p.time_ns / 1e9 for p in first) < 0.02


def _read_all(read, n, timeout=10.0):
    got = bytearray()
    deadline = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < deadline:
        got += read(n - len(got))
    return bytes(got)


def test_serial_loop_url_carries_the_frames_in_order():
    samples = _imus(60)
    port = serial.serial_for_url("loop://", timeout=0.05)
    player = SerialPlayer(port, speed=50.0, respond=False).add_samples(samples)
    expected = b"".join(player.mti.mtdata2(s) for s in samples)
    player.start()
    got = _read_all(port.read, len(expected))  # loop:// holds 4 KiB: read while it plays
    report = player.join()
    port.close()
    assert got == expected and report.sent == 60 and report.bytes_sent == len(expected)


def test_serial_over_a_pty_slave_port():
    master, slave = os.openpty()
    try:
        port = serial.Serial(os.ttyname(slave), baudrate=921600, timeout=0.05)  # raw mode
        player = SerialPlayer(port, speed=50.0).add_samples(_imus(80))
        expected = b"".join(player.mti.mtdata2(p.data) for p in player.packets)
        assert {0x0D, 0x11, 0x13, 0x7F} <= set(expected)  # CR, XON, XOFF, DEL: must pass unaltered
        player.start()
        got = _read_all(lambda n: os.read(master, n) if select.select([master], [], [], 0.05)[0] else b"",
                        len(expected))
        report = player.join()
        port.close()
    finally:
        os.close(master)
        os.close(slave)
    assert got == expected and report.sent == 80


def _frames_of(stream: bytes):
    """Complete Xbus frames (MID, data) in ``stream`` and the unparsed rest (own reading)."""
    out, i = [], 0
    while True:
        j = stream.find(b"\xfa\xff", i)
        if j < 0 or len(stream) < j + 4:
            return out, stream[i:]
        n, head = stream[j + 3], 4
        if n == 0xFF:
            n, head = struct.unpack(">H", stream[j + 4: j + 6])[0], 6
        end = j + head + n + 1
        if len(stream) < end:
            return out, stream[j:]
        assert sum(stream[j + 1: end]) % 256 == 0
        out.append((stream[j + 2], stream[j + head: end - 1]))
        i = end


class XbusHost:
    """The host end of the pty, with pyserial, collecting frames."""

    def __init__(self, path):
        self.port = serial.Serial(path, baudrate=921600, timeout=0.01)
        self.frames: list[tuple[int, bytes]] = []
        self._rest = b""

    def send(self, mid, data=b""):
        body = bytes([0xFF, mid, len(data)]) + data
        self.port.write(b"\xfa" + body + bytes([-sum(body) & 0xFF]))

    def read_until(self, mid, start=0, timeout=5.0):
        """Index of the first frame with ``mid`` at or after ``start``, reading as needed."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            new, self._rest = _frames_of(self._rest + self.port.read(4096))
            self.frames += new
            hits = [k for k, (m, _) in enumerate(self.frames) if m == mid and k >= start]
            if hits:
                return hits[0]
        raise AssertionError(f"no matching frame within {timeout} s; got MIDs {[m for m, _ in self.frames][-20:]}")


def test_xbus_configuration_dialogue_over_a_pty():
    with PtyMaster() as pty:
        host = XbusHost(pty.slave_path)
        player = SerialPlayer(pty, speed=1.0).add_samples(_imus(4000))  # 10 s at 400 Hz; stopped when done
        player.start()
        try:
            host.read_until(0x36)  # measuring from the start
            host.port.write(b"\x00\x01junk")  # garbage before a message is skipped
            host.send(0x30)  # GoToConfig
            ack = host.read_until(0x31)
            time.sleep(0.05)
            host.send(0x00)  # ReqDID
            did = host.read_until(0x01)
            assert all(m != 0x36 for m, _ in host.frames[ack + 1: did])  # config state: no data
            assert host.frames[did][1] == struct.pack(">L", player.mti.device_id)
            cfg = struct.pack(">HHHH", 0x1020, 0xFFFF, 0x2010, 400)
            host.send(0xC0, cfg)
            assert host.frames[host.read_until(0xC1)][1] == cfg
            host.send(0x7A)  # not a message an MTi knows
            assert host.frames[host.read_until(0x42)][1] == b"\x04"
            host.send(0x10)  # GoToMeasurement
            data = host.frames[host.read_until(0x36, start=host.read_until(0x11))][1]
            assert struct.unpack_from(">HB", data, 0) == (0x1020, 2)
            assert struct.unpack_from(">HB", data, 5) == (0x2010, 16)
            assert len(data) == 24  # only the configured records
        finally:
            player.stop()
            report = player.join()
            host.port.close()
    assert report.replies == 5 and len(report.suppressed) > 0 and not report.completed
    assert player.mti.bytes_skipped >= 6


def test_can_virtual_bus_carries_the_frames():
    channel = f"test-{uuid.uuid4().hex[:8]}"
    with can.Bus(interface="virtual", channel=channel) as tx, can.Bus(interface="virtual", channel=channel) as rx:
        player = CanPlayer(tx, speed=50.0).add_samples(_imus(50))
        expected = [(p.data.arbitration_id, bytes(p.data.data)) for p in player.packets]
        report = player.play()
        got = []
        while (m := rx.recv(timeout=0.2)) is not None:
            got.append((m.arbitration_id, bytes(m.data), m.is_extended_id))
    assert [(i, d) for i, d, _ in got] == expected and not any(e for *_, e in got)
    assert report.sent == 400 and [i for i, _ in expected[:8]] == [0x05, 0x06, 0x11, 0x21, 0x32, 0x34, 0x35, 0x41]


# ------------------------------------------------------------------------------------------ faults
FAULTS = Faults(seed=11, loss=0.1, reorder=0.05, max_displacement=4, duplicate=0.05, corrupt=0.05, corrupt_bytes=2)


def test_fault_rates_match_the_configuration():
    packets = [Packet(k * 4_000_000, b"x" * 64, "s") for k in range(20_000)]  # 80 s at 250 Hz
    plan = plan_faults(packets, FAULTS)
    n = len(packets)
    alive = n - len(plan.lost)
    assert abs(len(plan.lost) / n - 0.1) < 0.01
    assert abs(len(plan.duplicated) / alive - 0.05) < 0.007
    assert abs(len(plan.corrupt) / alive - 0.05) < 0.007
    assert abs(len(plan.reordered) / alive - 0.05) < 0.01  # slightly under: a packet held behind held ones
    assert max(plan.reordered.values()) <= 4
    assert len(plan.order) == alive + len(plan.duplicated)
    assert plan_faults(packets, FAULTS) == plan  # same seed, same faults
    other = plan_faults(packets, replace(FAULTS, seed=12))
    assert other.lost != plan.lost and other.corrupt != plan.corrupt
    # changing one rate leaves the other kinds' draws alone
    more_dup = plan_faults(packets, replace(FAULTS, duplicate=0.2))
    assert more_dup.lost == plan.lost and more_dup.corrupt == plan.corrupt


def _check_exact(received: list[bytes], originals: list[bytes], log, offset=0):
    """The received packets are the recorded ones: ``log.sent`` in order, each equal to its
    original except at exactly its recorded corrupted offsets (+ ``offset``); and the recorded
    sequence holds exactly the recorded losses, duplicates and reorderings."""
    assert len(received) == len(log.sent)
    for d, i in zip(received, log.sent):
        o = originals[i]
        assert len(d) == len(o)
        assert tuple(j for j in range(len(d)) if d[j] != o[j]) == tuple(x + offset for x in log.corrupted.get(i, ()))
    ids = log.sent
    assert set(range(len(originals))) - set(ids) == set(log.lost) | set(log.outage)
    assert not set(log.lost) & set(log.outage)
    twice = [i for i in set(ids) if ids.count(i) == 2]
    assert sorted(twice) == sorted(log.duplicated) and max(map(ids.count, ids)) <= 2
    assert all(ids[ids.index(i) + 1] == i for i in twice)  # the copy follows the original
    seen, late = [], {}
    for i in dict.fromkeys(ids):  # first arrival of each
        if any(j > i for j in seen):
            late[i] = sum(j > i for j in seen)
        seen.append(i)
    assert late == log.reordered
    assert set(log.corrupted) <= set(ids)


def test_faults_over_udp_affect_exactly_the_recorded_packets():
    packets = tracker_packets(_trackers("LHR-A", 600, hz=250.0))  # unique timestamps in every datagram
    rx = UdpReceiver()
    with UdpPlayer(rx.address, speed=25.0, faults=FAULTS) as player:
        player.add(packets)
        report = player.play()
    got = rx.wait_for(report.sent)
    log = report.faults
    assert len(got) == report.sent == len(log.sent)
    assert min(len(log.lost), len(log.duplicated), len(log.reordered), len(log.corrupted)) > 5
    assert all(len(v) == 2 for v in log.corrupted.values())
    originals = [p.data for p in packets]
    _check_exact(got, originals, log)
    # identified by content (every datagram holds its own timestamp), the intact ones agree
    for d, i in zip(got, log.sent):
        if i not in log.corrupted:
            assert originals.index(d) == i


def test_faults_over_can_are_reproducible_and_exact():
    channel = f"test-{uuid.uuid4().hex[:8]}"
    runs = []
    for _ in range(2):
        with can.Bus(interface="virtual", channel=channel) as tx, can.Bus(interface="virtual", channel=channel) as rx:
            player = CanPlayer(tx, speed=math.inf, faults=FAULTS).add_samples(_imus(150))
            report = player.play()
            got = []
            while (m := rx.recv(timeout=0.1)) is not None:
                got.append(struct.pack(">H", m.arbitration_id) + bytes(m.data))
        originals = [struct.pack(">H", p.data.arbitration_id) + bytes(p.data.data) for p in player.packets]
        _check_exact(got, originals, report.faults, offset=2)  # offsets count in the data field
        runs.append((got, report.faults))
    assert runs[0] == runs[1]  # same seed: same bytes, same log


def test_outage_silences_one_device_which_comes_back():
    packets = tracker_packets(_trackers("LHR-A", 250)) + tracker_packets(_trackers("LHR-B", 250))  # 1 s each
    faults = Faults(seed=1, outages=(Outage(0.2, 0.5, "vive/LHR-A"),))
    rx = UdpReceiver()
    with UdpPlayer(rx.address, speed=10.0, faults=faults) as player:
        player.add(packets)
        report = player.play()
    got = rx.wait_for(report.sent)
    stamps = {b"LHR-A": [], b"LHR-B": []}
    for d in got:
        stamps[d[8:40].rstrip(b"\0")].append(struct.unpack("<q", d[40:48])[0] / 1e9)
    a, b = np.array(stamps[b"LHR-A"]), np.array(stamps[b"LHR-B"])
    assert len(b) == 250 and len(a) == 250 - 75  # 0.3 s at 250 Hz silent
    assert not np.any((a >= 0.2) & (a < 0.5)) and a.max() > 0.9  # it came back
    assert len(report.faults.outage) == 75
    assert {player.packets[i].stream for i in report.faults.outage} == {"vive/LHR-A"}


def test_stop_ends_a_background_play_early():
    rx = UdpReceiver()
    with UdpPlayer(rx.address, speed=1.0) as player:
        player.add(tracker_packets(_trackers("LHR-A", 2500)))  # 10 s
        player.start()
        time.sleep(0.1)
        assert player.running
        player.stop()
        report = player.join(timeout=2.0)
    assert not player.running and not report.completed and 0 < report.sent < 2500
    assert rx.wait_for(report.sent) and len(rx.got) == report.sent

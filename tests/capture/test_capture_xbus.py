"""xbus:// — the Xbus parser and MTData2 decoder, and the serial source on a real pty and on
pyserial's loop://, against the simulated MTi (configuration dialogue, garbage, corrupt frames)."""

from __future__ import annotations

import math
import struct
import time
from collections import Counter

import numpy as np
import pytest
import serial
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.sources import RawPacket, SourceError, SourceLost, make_decoder, open_source
from dualhuman_builder.capture.wire.xbus import (MID, SimulatedMti, XbusParser, decode_mtdata2, encode_message,
                                                 encode_mtdata2, from_zup_wxyz)  # fmt: skip
from dualhuman_builder.capture.wire import to_zup_wxyz
from dualhuman_builder.capture.xbus_serial import SequenceTracker, XbusDecoder, XbusSource
from dualhuman_builder.sim.devices import Faults, Packet, PtyMaster, SerialPlayer
from dualhuman_builder.sim.imu import simulate_imu
from dualhuman_builder.sim.studio import XBUS_CLOCK
from dualhuman_builder.tracks import SkeletonTrack


def imu_samples(seconds=1.0, rate=400.0, first_counter=0, device="mti-xbus") -> list[ImuSample]:
    """A simulated MTi (sim/imu.py, the studio's Xbus clock) on a turning, bobbing pelvis."""
    t = np.arange(int(seconds * 60) + 2) / 60.0
    q = Rotation.from_rotvec(np.outer(np.sin(2 * np.pi * 0.5 * t), [0.3, 1.0, 0.2])).as_quat()[:, None]
    p = np.stack([0.1 * t, 0.95 + 0.02 * np.sin(6 * t), 0 * t], -1)[:, None]
    ns = np.round(t * 1e9).astype(np.int64)
    track = SkeletonTrack(("Pelvis",), q, p, ns, ns, fps=60.0)
    return list(simulate_imu(track, "Pelvis", rate, seed=1, clock=XBUS_CLOCK, device=device,
                             first_counter=first_counter))  # fmt: skip


def assert_same(got: ImuSample, want: ImuSample, device=None):
    """Equal within float32 (the wire's precision); device time within the 100 us tick."""
    assert got.device == (device or want.device)
    assert got.counter == want.counter and abs(got.device_time_ns - want.device_time_ns) <= 50_000
    np.testing.assert_allclose(got.orientation, want.orientation, atol=2e-7)
    for f in ("acceleration", "rate_of_turn", "magnetic_field"):
        np.testing.assert_array_equal(getattr(got, f), np.float32(getattr(want, f)).astype(np.float64))
    assert got.status == want.status


def read_all(src, until, idle_s=0.3, limit_s=15.0) -> list[RawPacket]:
    """Read ``src`` until ``until()`` is true and nothing has arrived for ``idle_s``."""
    out, last, end = [], time.monotonic(), time.monotonic() + limit_s
    while time.monotonic() < end:
        got = src.read(0.05)
        out += got
        if got:
            last = time.monotonic()
        elif until() and time.monotonic() - last > idle_s:
            break
    return out


def decode(decoder, packets) -> list[ImuSample]:
    return [s for p in packets for s in decoder.feed(p)] + decoder.finish()


# ------------------------------------------------------------------------------------------ parser
def test_parser_any_chunking_garbage_and_extended_length():
    frames = [encode_message(0x31), encode_message(0x36, bytes(range(40))), encode_message(0x36, bytes(300) + b"\x01")]
    garbage = b"\x00\x13no-preamble\xfa"  # ends in a lone FA: kept until the next byte says it is not a frame
    stream = garbage + frames[0] + b"junk" + frames[1] + frames[2]
    expected = [(0x31, b""), (0x36, bytes(range(40))), (0x36, bytes(300) + b"\x01")]
    rng = np.random.default_rng(3)
    for chunks in ([1] * len(stream), rng.integers(1, 40, 200).tolist(), [len(stream)]):
        p, got, i = XbusParser(), [], 0
        for n in chunks:
            got += p.feed(stream[i: i + n])
            i += n
            if i >= len(stream):
                break
        assert got == expected
        assert p.frames == 3 and p.counters["bytes_skipped"] == len(garbage) + 4 and p.counters["resyncs"] == 2
        assert p.pending == 0
    p = XbusParser()
    assert p.feed(frames[2][:-1]) == [] and p.pending == len(frames[2]) - 1  # a partial frame waits
    assert p.feed(frames[2][-1:]) == [expected[2]]


def test_parser_bad_checksum_and_lengths_that_cannot_be_valid():
    good = encode_message(0x36, b"\x01\x02\x03")
    bad = bytearray(encode_message(0x36, b"\x09" * 8))
    bad[-1] ^= 0x55
    p = XbusParser()
    # a frame hidden one byte after a bad preamble is still found
    hidden = b"\xfa" + good
    assert p.feed(bytes(bad) + hidden) == [(0x36, b"\x01\x02\x03")]
    assert p.counters["bad_checksum"] == 1 and p.counters["bytes_skipped"] == len(bad) + 1
    # a length of 65535 is legal by the format but never waited for beyond max_length
    q = XbusParser(max_length=4096)
    huge = b"\xfa\xff\x36\xff\xff\xff"
    assert q.feed(huge + good) == [(0x36, b"\x01\x02\x03")]
    assert q.counters["bad_length"] == 1 and q.pending == 0
    # an extended length of 254 or less is not a form the format allows
    r = XbusParser()
    assert r.feed(b"\xfa\xff\x36\xff\x00\x03\x01\x02\x03\xc4" + good) == [(0x36, b"\x01\x02\x03")]
    assert r.counters["bad_length"] == 1
    # the default parser waits for 65535 claimed bytes without allocating for them
    s = XbusParser()
    assert s.feed(huge) == [] and s.pending == len(huge) and len(s._buf) == len(huge)
    # a cut frame swallowing the next ones: given up by flush (no more bytes are coming)
    t = XbusParser()
    assert t.feed(encode_message(0x36, bytes(80))[:20] + encode_message(0x31)) == []
    assert t.flush() == [(0x31, b"")] and t.counters["cut_frames"] == 1 and t.pending == 0


def test_simulated_mti_uses_the_parser():
    mti = SimulatedMti()
    reply = mti.answer(b"\x00junk" + encode_message(0x30)[:3])
    assert reply == b"" and mti.bytes_skipped == 5
    assert mti.answer(encode_message(0x30)[3:]) == encode_message(0x31) and mti.frames_received == 1


# ------------------------------------------------------------------------------------------ records
def test_decode_mtdata2_precision_unknown_ids_sizes_and_truncation():
    q = to_zup_wxyz([0.1, 0.2, 0.3, math.sqrt(1 - 0.14)])
    data = (struct.pack("!HB4d", 0x2013, 32, *q)  # float64 quaternion
            + struct.pack("!HBH", 0x1020, 2, 7)
            + struct.pack("!HB5s", 0x7770, 5, b"abcde")  # unknown: skipped by its size
            + struct.pack("!HB3f", 0x4021, 12, 1, 2, 3)  # fixed-point 12.20: unsupported
            + struct.pack("!HBH", 0x1060, 2, 1)  # SampleTimeFine must be 4 bytes
            + struct.pack("!HB3d", 0x8023, 24, 0.1, 0.2, 0.3)
            + struct.pack("!HB", 0xC020, 12) + b"\x00" * 5)  # fmt: skip  # runs past the end
    counters = Counter()
    rec = decode_mtdata2(data, counters)
    assert set(rec) == {0x2010, 0x1020, 0x8020}
    assert rec[0x2010] == tuple(q) and rec[0x1020] == (7,) and rec[0x8020] == (0.1, 0.2, 0.3)
    assert counters == Counter(unknown_id=1, unsupported_precision=1, bad_record_size=1, truncated=1)
    np.testing.assert_allclose(from_zup_wxyz(*rec[0x2010]), [0.1, 0.2, 0.3, math.sqrt(1 - 0.14)], atol=1e-15)
    assert decode_mtdata2(b"\x10", counters) == {} and counters["truncated"] == 2


def test_float64_frames_decode_alike_on_the_first_and_the_compiled_path():
    samples = imu_samples(0.05)[:3]

    def frame(s):  # every record in float64 precision (ID | 3)
        return encode_message(0x36, struct.pack(
            "!HBH HBL HB4d HB3d HB3d HB3d HBL", 0x1020, 2, s.counter, 0x1060, 4, s.device_time_ns // 100_000,
            0x2013, 32, *to_zup_wxyz(s.orientation), 0x4023, 24, *s.acceleration, 0x8023, 24, *s.rate_of_turn,
            0xC023, 24, *s.magnetic_field, 0xE020, 4, 5))  # fmt: skip

    d = XbusDecoder("imu")
    got = decode(d, [RawPacket(k, frame(s)) for k, s in enumerate(samples)])
    for g, s in zip(got, samples, strict=True):
        assert g.counter == s.counter and g.device_time_ns == s.device_time_ns and g.status == 5
        np.testing.assert_allclose(g.orientation, s.orientation, atol=1e-15)
        for f in ("acceleration", "rate_of_turn", "magnetic_field"):
            np.testing.assert_array_equal(getattr(g, f), getattr(s, f))  # float64: exact
    assert len(d._layouts) == 1 and d.counters["incomplete"] == 0


def test_decoder_counts_loss_duplicates_missing_records_and_errors():
    samples = imu_samples(0.1)
    d = XbusDecoder("imu")
    order = [0, 1, 2, 5, 3, 3, 6, 7, 7, 8]  # 4 never comes; 3 late; 3 and 7 twice
    got = decode(d, [RawPacket(100 + k, encode_mtdata2(samples[i])) for k, i in enumerate(order)])
    assert [s.counter for s in got] == [0, 1, 2, 5, 3, 6, 7, 8]
    assert d.counters["lost"] == 1 and d.counters["duplicate"] == 2 and d.counters["out_of_order"] == 1
    assert [s.host_time_ns for s in got] == [100, 101, 102, 103, 104, 106, 107, 109]
    for s in got:
        assert_same(s, samples[s.counter], device="imu")
    # records missing: NaN fields, counted; acks and errors counted by MID, errors reported
    only = encode_mtdata2(samples[9], outputs=[0x1020, 0x1060, 0x4020])
    stream = only + encode_message(MID.GO_TO_CONFIG_ACK) + encode_message(MID.ERROR, b"\x28")
    (s,) = d.feed(RawPacket(200, stream))
    assert s.counter == 9 and s.device_time_ns == samples[9].device_time_ns
    assert np.isnan(s.orientation).all() and np.isnan(s.rate_of_turn).all() and np.isnan(s.magnetic_field).all()
    assert np.isfinite(s.acceleration).all() and s.status == 0
    c = d.counters
    assert c["incomplete"] == 1 and c["mid_0x31"] == 1 and c["mid_0x42"] == 1 and c["samples"] == 9
    (event,) = d.pop_events()
    assert event.kind == "device-error" and "0x28 (device error)" in event.message and event.entity == "imu"
    assert d.status(200)["imu"] == {"last_ns": 200, "live": True}
    # a cut frame at the end of the stream hides a complete one: finish() finds it
    assert d.feed(RawPacket(300, encode_message(0x36, bytes(300))[:30] + encode_mtdata2(samples[11]))) == []
    (s,) = d.finish()
    assert s.counter == 11 and s.host_time_ns == 300 and d.counters["cut_frames"] == 1


def test_an_empty_mtdata2_frame_is_counted_and_decoding_goes_on():
    samples = imu_samples(0.05)[:6]
    frames = [encode_mtdata2(s) for s in samples]
    empty = bytes.fromhex("FAFF3600CB")
    assert empty == encode_message(MID.MT_DATA2)
    for at in (0, 3):  # before the first layout is compiled, and after
        d = XbusDecoder("imu")
        stream = frames[:at] + [empty] + frames[at:]
        got = decode(d, [RawPacket(k, f) for k, f in enumerate(stream)])
        assert [g.counter for g in got] == [s.counter for s in samples]
        assert d.counters["empty_frame"] == 1 and d.counters["packets"] == 7 and d.counters["frames"] == 7
        assert d.counters["decoder_errors"] == 0 and d.pop_events() == []


def test_an_empty_frame_in_a_take_replays_and_verifies(tmp_path):
    from dualhuman_builder.capture.log.writer import TakeWriter
    from dualhuman_builder.capture.replay import redecode, verify_replay

    samples = imu_samples(0.05)[:8]
    chunks = [encode_mtdata2(s) for s in samples]
    chunks[4] = chunks[4] + bytes.fromhex("FAFF3600CB")  # the empty frame inside one serial read
    path = tmp_path / "take.mcap"
    w = TakeWriter(path, take="t", sources=[("imu", "xbus://loop", "xbus")])
    d = make_decoder("xbus://loop")
    for k, c in enumerate(chunks):
        p = RawPacket(1_000 + k, c)
        w.add_raw(0, p)
        for s in d.feed(p):
            w.add_sample(0, s)
    for s in d.finish():
        w.add_sample(0, s)
    w.close()
    assert [s.counter for _, s in redecode(path)] == [s.counter for s in samples]
    check = verify_replay(path)
    assert check.samples == len(samples) and check.identical


def _frame(q_wxyz, acc, gyr=(0.1, 0.2, 0.3), mag=(0.3, 0.0, 0.4), counter=0, precision=0):
    f = "d" if precision else "f"
    size = 8 if precision else 4
    return encode_message(MID.MT_DATA2, struct.pack(
        f"!HBH HBL HB4{f} HB3{f} HB3{f} HB3{f} HBL", 0x1020, 2, counter, 0x1060, 4, 100 * counter,
        0x2010 | precision, 4 * size, *q_wxyz, 0x4020 | precision, 3 * size, *acc, 0x8020 | precision, 3 * size, *gyr,
        0xC020 | precision, 3 * size, *mag, 0xE020, 4, 0))  # fmt: skip


def test_non_finite_or_non_unit_values_are_counted_not_passed_on():
    nan, inf = float("nan"), float("inf")
    good_q, good_acc = (1.0, 0.0, 0.0, 0.0), (0.0, 0.0, 9.81)
    for precision in (0, 3):  # float32 and float64 records
        d = XbusDecoder("imu")
        frames = [_frame(good_q, good_acc, counter=0, precision=precision),  # compiles the layout
                  _frame((nan, 0, 0, 0), good_acc, counter=1, precision=precision),
                  _frame((inf, 0, 0, 0), (inf, 0, 0), counter=2, precision=precision),
                  _frame(good_q, (0, nan, 0), mag=(-inf, 0, 0), counter=3, precision=precision),
                  _frame((2.0, 0, 0, 0), good_acc, counter=4, precision=precision),  # a norm of 2: no rotation
                  _frame(good_q, good_acc, counter=5, precision=precision)]  # fmt: skip
        got = decode(d, [RawPacket(k, f) for k, f in enumerate(frames)])
        assert [g.counter for g in got] == [0, 1, 2, 3, 4, 5]  # counters and times are kept
        for g in got:
            for v in (g.orientation, g.acceleration, g.rate_of_turn, g.magnetic_field):
                assert np.isfinite(v).all() or np.isnan(v).all()
        assert [bool(np.isnan(g.orientation).all()) for g in got] == [False, True, True, False, True, False]
        assert [bool(np.isnan(g.acceleration).all()) for g in got] == [False, False, True, True, False, False]
        assert np.isnan(got[3].magnetic_field).all() and np.isfinite(got[3].rate_of_turn).all()
        c = d.counters
        assert c["bad_quaternion"] == 3 and c["bad_vector"] == 3 and c["incomplete"] == 0 and c["samples"] == 6
        np.testing.assert_allclose(got[5].orientation, from_zup_wxyz(*good_q), atol=1e-7)
        # the slow path (a frame of a length never seen) checks alike
        d2 = XbusDecoder("imu")
        (g,) = decode(d2, [RawPacket(0, _frame((nan, 0, 0, 0), (inf, 0, 0), precision=precision))])
        assert np.isnan(g.orientation).all() and np.isnan(g.acceleration).all()
        assert d2.counters["bad_quaternion"] == 1 and d2.counters["bad_vector"] == 1


def test_sample_time_fine_and_packet_counter_unwrap():
    base = imu_samples(0.2, first_counter=65500)
    wrap_ticks = 2**32
    shift = (wrap_ticks - 100) * 100_000 - base[0].device_time_ns  # cross the u32 tick wrap after 4 samples
    samples = [ImuSample(s.device, s.counter, s.device_time_ns + shift, s.host_time_ns, s.orientation, s.acceleration,
                         s.rate_of_turn, s.magnetic_field) for s in base]  # fmt: skip
    d = XbusDecoder("mti-xbus")
    got = decode(d, [RawPacket(k, encode_mtdata2(s)) for k, s in enumerate(samples)])
    assert len(got) == len(samples) > 70
    assert [g.device_time_ns for g in got] == [s.device_time_ns for s in samples]  # beyond 2**32 ticks
    assert got[-1].device_time_ns > wrap_ticks * 100_000
    assert got[0].counter == 65500 and got[-1].counter == (65500 + len(samples) - 1) % 65536 < 100
    assert d.counters["lost"] == 0 and d.counters["out_of_order"] == 0 and d.counters["duplicate"] == 0


def test_sequence_tracker_window():
    t, c = SequenceTracker(16, window=8), Counter()
    assert all(t.update(v, c) for v in (65534, 65535, 0, 3))  # wraps; 1 and 2 lost
    assert c["lost"] == 2 and t.update(1, c) and c == Counter(lost=1, out_of_order=1)
    assert not t.update(3, c) and c["duplicate"] == 1


# ------------------------------------------------------------------------------------------ source
class ChattyMti(SimulatedMti):
    """Still streams three data frames (the last one cut short) before it acknowledges GoToConfig,
    as a measuring device does."""

    def _reply(self, mid, data):
        if mid == MID.GO_TO_CONFIG:
            frames = b"".join(encode_mtdata2(s) for s in imu_samples(0.01)[:3])
            return frames + frames[:20] + super()._reply(mid, data)
        return super()._reply(mid, data)


def test_round_trip_over_a_pty_with_the_configuration_dialogue():
    samples = imu_samples(2.0)
    with PtyMaster() as pty:
        player = SerialPlayer(pty, speed=4.0, linger_s=0.5, mti=ChattyMti()).add_samples(samples)
        player.start()
        src = XbusSource(f"xbus://{pty.slave_path}?baud=921600&timeout=3&device=mti-xbus")
        try:
            events = src.decoder.pop_events()
            packets = read_all(src, lambda: not player.running)
            got = decode(src.decoder, packets)
        finally:
            src.close()
            player.stop()
            report = player.join()
    assert [e.kind for e in events] == ["configured"]
    assert player.mti.outputs == (0x1020, 0x1060, 0x2010, 0x4020, 0x8020, 0xC020, 0xE020)
    assert report.replies == 3 and len(got) > 400  # GoToConfig, SetOutputConfiguration, GoToMeasurement
    first = got[0].counter
    assert [s.counter for s in got] == list(range(first, len(samples)))  # everything after the ack, in order
    for s in got:
        assert_same(s, samples[s.counter])
    host = [s.host_time_ns for s in got]
    assert host == sorted(host) and set(host) <= {p.host_time_ns for p in packets}
    stats = src.stats()
    assert stats.get("lost", 0) == stats.get("bad_checksum", 0) == 0 and stats["samples"] == len(got)
    assert stats["read_bytes"] == stats["bytes"] > 0 and stats["dialogue_skipped_frames"] >= 3


def test_garbage_and_corrupt_frames_are_counted_and_the_rest_decodes():
    samples = imu_samples(0.5)
    garbage = b"\x00noise\x13\x11\r\n"
    with PtyMaster() as pty:
        port = serial.Serial(pty.slave_path, baudrate=921600, timeout=0.05)
        src = XbusSource(f"xbus://{pty.slave_path}?config=0&device=mti-xbus", port=port)
        player = SerialPlayer(pty, speed=math.inf, faults=Faults(seed=5, corrupt=0.05, corrupt_bytes=1))
        player.add_samples(samples)
        player.add(Packet(s.device_time_ns, garbage, "noise") for s in samples[10::40])
        player.start()
        got = decode(src.decoder, read_all(src, lambda: not player.running))
        report = player.join()
        src.close()
        port.close()
    corrupted = {player.packets[i].data.counter for i in report.faults.corrupted if player.packets[i].stream != "noise"}
    assert len(corrupted) >= 5
    assert [s.counter for s in got] == [s.counter for s in samples if s.counter not in corrupted]
    for s in got:
        assert_same(s, samples[s.counter])
    c = src.decoder.counters
    ends = {samples[0].counter, samples[-1].counter}
    assert c["lost"] == len(corrupted - ends) and c["duplicate"] == 0
    assert c["bad_checksum"] + c["bad_length"] + c["resyncs"] >= len(corrupted)
    assert c["bytes_skipped"] >= len(garbage) * len(samples[10::40])


def test_a_device_that_never_answers_names_the_step():
    with PtyMaster() as pty:
        t0 = time.monotonic()
        with pytest.raises(SourceError, match=r"no reply to GoToConfig .* within 0.3 s.*config=0"):
            XbusSource(f"xbus://{pty.slave_path}?timeout=0.3")
        assert time.monotonic() - t0 < 2.0
        # a device streaming data but not listening: the data frames do not count as an ack
        player = SerialPlayer(pty, speed=1.0, respond=False).add_samples(imu_samples(1.0))
        player.start()
        try:
            with pytest.raises(SourceError, match="no reply to GoToConfig"):
                XbusSource(f"xbus://{pty.slave_path}?timeout=0.3")
        finally:
            player.stop()
            player.join()


class StubbornMti(SimulatedMti):
    """Acknowledges GoToConfig but stays measuring (a faulty device)."""

    def _reply(self, mid, data):
        if mid == MID.GO_TO_CONFIG:
            return encode_message(MID.GO_TO_CONFIG_ACK)
        return super()._reply(mid, data)


def test_an_error_reply_names_the_step_and_the_code():
    with PtyMaster() as pty:
        player = SerialPlayer(pty, speed=1.0, mti=StubbornMti()).add_samples(imu_samples(1.0))
        player.start()
        try:
            with pytest.raises(SourceError, match=r"SetOutputConfiguration failed .* Error 0x04 \(invalid message\)"):
                XbusSource(f"xbus://{pty.slave_path}?timeout=2")
        finally:
            player.stop()
            player.join()


def test_closing_the_pty_while_reading_is_source_lost():
    pty = PtyMaster()
    src = open_source(f"xbus://{pty.slave_path}?config=0")
    pty.write(encode_mtdata2(imu_samples(0.01)[0]))
    assert len(decode(src.decoder, read_all(src, lambda: True, idle_s=0.1))) == 1
    pty.close()
    with pytest.raises(SourceLost, match=f"serial port {pty.slave_path} failed while reading"):
        for _ in range(20):
            src.read(0.05)
    src.close()
    assert src.read(0.05) == []


def test_loop_url_with_config_0():
    samples = imu_samples(0.25)
    port = serial.serial_for_url("loop://", timeout=0.05)
    src = XbusSource("xbus://loop?device=mti-loop", port=port)  # loop://: no dialogue by default
    player = SerialPlayer(port, speed=20.0, respond=False).add_samples(samples)
    player.start()
    got = decode(src.decoder, read_all(src, lambda: not player.running))
    player.join()
    src.close()
    assert [s.counter for s in got] == [s.counter for s in samples]
    for s in got:
        assert_same(s, samples[s.counter], device="mti-loop")
    own = open_source("xbus://loop")  # opens its own loop:// port
    assert own.decoder.device == "loop" and own.read(0.01) == []
    own.close()


def test_urls_and_open_errors():
    assert make_decoder("xbus:///dev/ttyUSB0?baud=921600").device == "ttyUSB0"
    assert make_decoder("xbus:///dev/pts/7?device=prop").device == "prop"
    for url, match, fix in (("xbus:///dev/ttyUSB0?parity=N", "unknown xbus:// parameter", "use only baud"),
                            ("xbus://dev/ttyUSB0", "names a host", "three slashes"),
                            ("xbus://", "names no serial port", "xbus:///dev/ttyUSB0"),
                            ("xbus://loop?config=yes", "config='yes'", "config=1"),
                            ("xbus://loop?baud=fast", "not an? int", "as a number"),
                            ("xbus:///dev/ttyNOPE9", "cannot open serial port /dev/ttyNOPE9",
                             "plugged in")):  # fmt: skip
        with pytest.raises(SourceError, match=match) as e:
            open_source(url)
        assert fix in str(e.value)


"""The guard every decoder sits behind (sources.Decoder): nothing raises out of feed, finish or
status, a fault is counted and reported and decoding goes on; events are coalesced so a flood keeps
memory bounded; one source's failure in the decoding process leaves the others decoding (a real
DecodeProcess)."""

from __future__ import annotations

import time

import numpy as np

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.decoding import DecodeProcess, _Lanes
from dualhuman_builder.capture.log.writer import SampleEncoder
from dualhuman_builder.capture.mvn_udp import MvnDecoder
from dualhuman_builder.capture.samples import ImuSample, SuitFrame
from dualhuman_builder.capture.sources import (EVENT_BURST, EVENT_INTERVAL_NS, MAX_EVENT_KEYS, MAX_HELD_EVENTS,
                                               Decoder, RawPacket, make_decoder)  # fmt: skip
from dualhuman_builder.capture.wire.mvn import encode_pose
from dualhuman_builder.capture.wire.xbus import encode_message, encode_mtdata2


class Fragile(Decoder):
    """Decodes ``b"ok"`` packets to their host time; ``b"!"`` raises half-way through a frame
    (``partial`` is its partial state, which :meth:`recover` drops)."""

    def __init__(self):
        super().__init__()
        self.partial = b""
        self.recovered = 0

    def feed(self, packet):
        self.counters["packets"] += 1
        self.partial += packet.data
        if packet.data == b"!":
            raise KeyError("record 0x1234 " + "x" * 5000)
        if packet.data == b"gen":
            return (t for t in (1, 2))  # not a list: the guard makes it one
        out = [packet.host_time_ns] if packet.data == b"ok" else []
        self.partial = b""
        return out

    def finish(self):
        raise ZeroDivisionError("at the end")

    def status(self, now_ns):
        raise RuntimeError("no status")

    def recover(self):
        self.partial = b""
        self.recovered += 1


class Stricter(Fragile):
    def feed(self, packet):  # a subclass of a guarded decoder, calling the guarded parent
        return super().feed(packet) + ["extra"]


def test_a_raising_decoder_is_counted_reported_and_goes_on():
    dec = Fragile()
    assert dec.feed(RawPacket(1, b"ok")) == [1]
    assert dec.feed(RawPacket(2, b"!")) == []  # raised inside: nothing escapes
    assert dec.partial == b"" and dec.recovered == 1  # the partial state was dropped
    assert dec.feed(RawPacket(3, b"ok")) == [3]  # and the next packet decodes
    assert dec.feed(RawPacket(4, b"gen")) == [1, 2]
    assert dec.finish() == [] and dec.status(5) == {}
    assert dec.counters["decoder_errors"] == 3 and dec.counters["packets"] == 4
    events = dec.pop_events()
    assert [e.kind for e in events] == ["decoder-error"] * 3
    first = events[0]
    assert first.entity == "Fragile" and first.host_time_ns == 2
    assert "Fragile.feed raised KeyError at test_decoder_guard.py:" in first.message
    assert "Traceback" not in first.message and len(first.message) < 500
    assert "ZeroDivisionError" in events[1].message and "RuntimeError" in events[2].message
    # a subclass of a subclass: the guard holds at each level
    sub = Stricter()
    assert sub.feed(RawPacket(1, b"!")) == ["extra"] and sub.counters["decoder_errors"] == 1


def test_every_built_in_decoder_is_guarded():
    for url in ("xbus://loop", "mti+can://virtual/x", "vive+usb://", "mvn+udp://127.0.0.1:9763",
                "vive+udp://127.0.0.1:8051"):  # fmt: skip
        cls = type(make_decoder(url))
        assert getattr(cls.feed, "_decoder_guard", False), cls
        assert getattr(cls.finish, "_decoder_guard", False), cls


def test_repeated_events_are_coalesced_and_memory_stays_bounded():
    dec = Fragile()
    n = 20_000
    for k in range(n):  # one event per ms of host time for 20 s
        dec.event(k * 1_000_000, "counter-reset", "mvn/0", f"counter jumped to {k}")
    kept = dec.events
    assert len(kept) <= EVENT_BURST + n * 1_000_000 // EVENT_INTERVAL_NS + 1
    assert [e.message for e in kept[:EVENT_BURST]] == [f"counter jumped to {k}" for k in range(EVENT_BURST)]
    assert "left out since the last one kept" in kept[-1].message
    assert dec.counters["events_suppressed"] == n - len(kept)
    dec.finish()  # the ones left out since the last kept event: one summary
    assert "more event(s) like it left out" in dec.events[-1].message
    assert dec.events[-1].message.endswith(f"counter jumped to {n - 1}")
    # another (kind, entity) has its own budget
    dec.pop_events()
    dec.event(0, "stale", "mvn/1", "quiet")
    assert [e.kind for e in dec.events] == ["stale"]


def test_distinct_entities_and_undrained_events_are_bounded():
    dec = Fragile()
    for k in range(3 * MAX_EVENT_KEYS):  # invented entities (e.g. forged serials)
        dec.event(k, "other-serial", f"vive/FAKE{k}", "dropped")
    assert len(dec._event_keys) <= MAX_EVENT_KEYS + 1
    assert len(dec.events) <= MAX_EVENT_KEYS + EVENT_BURST
    dec.finish()
    assert "of other kinds or entities left out" in dec.events[-1].message
    # nobody drains them (a replay that only wants samples): held events stop at MAX_HELD_EVENTS
    dec = Fragile()
    for k in range(MAX_HELD_EVENTS + 50):
        dec.event(k * EVENT_INTERVAL_NS, "gap", "dev", "a gap")
    assert len(dec.events) == MAX_HELD_EVENTS and dec.counters["events_dropped"] == 50


def test_a_counter_alternating_between_far_apart_values_does_not_keep_an_event_per_datagram():
    s = len(MVN_SEGMENTS)
    q, p = np.tile([0.0, 0.0, 0.0, 1.0], (s, 1)), np.zeros((s, 3))
    dec = MvnDecoder()
    n = 2000
    for k in range(n):
        counter = k // 2 + (50_000_000 if k % 2 else 0)
        frame = SuitFrame(0, counter, k, k * 1_000_000, 0, tuple(MVN_SEGMENTS), q, p)
        for d in encode_pose(frame):
            dec.feed(RawPacket(k * 1_000_000, d))
    dec.finish()
    assert dec.counters["packets"] == n
    assert len(dec.events) <= 3 * (EVENT_BURST + 1)


# --------------------------------------------------------------------------------- decoding process
def xbus_stream(n: int) -> list[bytes]:
    out = []
    for k in range(n):
        s = ImuSample("loop", k, k * 10_000_000, 0, np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 9.81, 0.0]),
                      np.zeros(3), np.array([0.3, 0.0, 0.4]), 0)  # fmt: skip
        out.append(encode_mtdata2(s))
    return out


class Unwritable(Decoder):
    """Decodes every packet to something the take writer cannot encode."""

    def feed(self, packet):
        return [object()]


def test_one_source_that_cannot_be_decoded_leaves_the_others_decoding():
    frames = xbus_stream(20)
    frames.insert(10, encode_message(0x36))  # an empty MTData2 frame in the middle
    dp = DecodeProcess(["nosuch://device", "xbus://loop"], ["broken", "imu"], {}, 0.0)
    try:
        dp.submit(0, [RawPacket(1, b"anything")] * 3)
        for k, f in enumerate(frames):
            dp.submit(1, [RawPacket(100 + k, f)])
        dp.submit(0, [RawPacket(2, b"more")])
        got = []
        dp.finish(got.append, timeout=60.0)
    finally:
        dp.close()
    assert dp.error is None
    samples = [it for m in got if m[1] == 1 for it in m[2] if it[0] == "msg"]
    assert len(samples) == 20
    events = [(m[1], e.kind, e.entity) for m in got for e in m[3]]
    assert (0, "decoding-failed", "broken") in events
    msg = next(e.message for m in got for e in m[3] if e.kind == "decoding-failed")
    assert "SourceError" in msg and "nosuch" in msg
    assert dp.counters[0]["decoding_failed"] == 1 and dp.counters[0]["undecoded_packets"] == 4
    assert dp.counters[1]["samples"] == 20 and dp.counters[1]["empty_frame"] == 1
    assert "decoder_errors" not in dp.counters[1]


def test_a_sample_the_writer_cannot_encode_stops_that_source_only():
    def build(url):
        return Unwritable() if url == "test://unwritable" else make_decoder(url)

    encoder = SampleEncoder(["bad", "imu"], {}, 0.0)
    lanes = _Lanes(["test://unwritable", "xbus://loop"], ["bad", "imu"], build, encoder.encode)
    t0 = time.monotonic_ns()
    bad = lanes.feed(0, [(t0, b"x"), (t0 + 1, b"y")])
    assert bad[2] == [] and [e.kind for e in bad[3]] == ["decoding-failed"]
    assert lanes.feed(0, [(t0 + 2, b"z")])[3] == []  # failed once, reported once
    good = lanes.feed(1, [(t0, f) for f in xbus_stream(3)])
    assert sum(it[0] == "msg" for it in good[2]) == 3
    counters = lanes.counters()
    assert counters[0]["decoding_failed"] == 1 and counters[0]["undecoded_packets"] == 1
    assert counters[1]["samples"] == 3
    assert [m[2] for m in lanes.finish()] == [[], []] and lanes.leftover() == []


def test_a_decoding_process_behind_the_packets_calls_no_device_silent():
    """Packets queued faster than they are decoded (host times 3 s in the past when decoded):
    liveness is judged at the time decoding has reached, so no ``stale`` event is invented."""
    s = len(MVN_SEGMENTS)
    q, p = np.tile([0.0, 0.0, 0.0, 1.0], (s, 1)), np.zeros((s, 3))
    t0 = time.monotonic_ns() - 3_000_000_000
    dp = DecodeProcess(["mvn+udp://127.0.0.1:9763"], ["suit"], {}, 0.0)
    try:
        for k in range(120):  # 1 s of poses at 120 Hz, one message each: a backlog before the process is up
            t = t0 + k * 8_333_333
            frame = SuitFrame(0, k, k, t, 0, tuple(MVN_SEGMENTS), q, p)
            dp.submit(0, [RawPacket(t, d) for d in encode_pose(frame)])
        got = []
        dp.finish(got.append, timeout=60.0)
    finally:
        dp.close()
    assert dp.counters[0]["samples"] == 120
    kinds = [e.kind for m in got for e in m[3]]
    assert "stale" not in kinds, kinds


def test_the_decoding_side_does_not_load_torch():
    """The decoding process imports the decoders and the sample encoder only: no torch or anny (seconds
    and hundreds of MB per process), though the MVN wire format names the body's segments."""
    import subprocess
    import sys

    code = ("import sys\n"
            "import dualhuman_builder.capture.decoding, dualhuman_builder.capture.log.writer\n"
            "from dualhuman_builder.capture.sources import make_decoder\n"
            "for u in ['mvn+udp://127.0.0.1:9763', 'vive+udp://127.0.0.1:8051', 'xbus://loop', 'mti+can://virtual/ch0',"
            " 'vive+usb://']:\n"
            "    make_decoder(u)\n"
            "print(sorted(m for m in ('torch', 'anny') if m in sys.modules))\n")  # fmt: skip
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "[]"

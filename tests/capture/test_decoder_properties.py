"""Property-based tests (Hypothesis) of the Xbus, MTi CAN and VIVE USB decoders: arbitrary bytes,
valid streams built with the wire encoders then mutated, any chunking. The decoders' own code never
raises (the guard of sources.Decoder would hide it, so ``decoder_errors`` must stay 0), every packet
and byte is counted, outputs and events stay bounded, and no NaN or infinity passes as a value."""

from __future__ import annotations

import itertools
import math

import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from dualhuman_builder.capture.mti_can import MtiCanDecoder
from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.sources import EVENT_BURST, RawPacket
from dualhuman_builder.capture.vive_usb import ViveUsbDecoder
from dualhuman_builder.capture.wire.mti_can import encode_can, pack_can_frame
from dualhuman_builder.capture.wire.vive_hid import IMU_REPORT_ID, REPORT_SIZE, HidImuSample, encode_imu_report
from dualhuman_builder.capture.wire.xbus import DEFAULT_OUTPUTS, encode_message, encode_mtdata2
from dualhuman_builder.capture.xbus_serial import MAX_FRAME_DATA, QUATERNION_NORM_TOLERANCE, XbusDecoder

#: Kinds of events a decoder of these three may log: each may keep a burst and a summary.
EVENT_BOUND = 4 * (EVENT_BURST + 1)


# ------------------------------------------------------------------------------------ strategies
@st.composite
def unit_quaternions(draw):
    q = np.array(draw(st.tuples(*[st.floats(-1, 1, allow_nan=False)] * 4)))
    n = np.linalg.norm(q)
    return np.array([0.0, 0.0, 0.0, 1.0]) if n < 0.1 else q / n


vectors = st.tuples(*[st.floats(-100, 100, allow_nan=False, width=32)] * 3).map(np.array)


@st.composite
def imu_samples(draw, n_max=6):
    n = draw(st.integers(1, n_max))
    first = draw(st.integers(0, 0xFFFF))
    t0 = draw(st.integers(0, 2**40))
    return [ImuSample("imu", (first + k) & 0xFFFF, t0 + k * 2_500_000, 0, draw(unit_quaternions()), draw(vectors),
                      draw(vectors), draw(vectors), draw(st.integers(0, 2**32 - 1))) for k in range(n)]  # fmt: skip


@st.composite
def mutated(draw, data: bytes) -> bytes:
    """``data`` with a few byte flips, deletions, insertions and repeats."""
    out = bytearray(data)
    for _ in range(draw(st.integers(0, 4))):
        op = draw(st.sampled_from(["flip", "delete", "insert", "repeat"]))
        i = draw(st.integers(0, len(out)))
        j = draw(st.integers(i, min(len(out), i + 40)))
        if op == "flip" and i < len(out):
            out[i] = draw(st.integers(0, 255))
        elif op == "delete":
            del out[i:j]
        elif op == "insert":
            out[i:i] = draw(st.binary(max_size=12))
        else:
            out[i:i] = out[i:j]
    return bytes(out)


@st.composite
def chunked(draw, data: bytes) -> list[bytes]:
    """``data`` cut at arbitrary points (empty reads included)."""
    cuts = sorted(draw(st.lists(st.integers(0, len(data)), max_size=12)))
    bounds = [0, *cuts, len(data)]
    return [data[a:b] for a, b in itertools.pairwise(bounds)]


def feed_all(dec, chunks: list[bytes]) -> list:
    out = []
    for k, c in enumerate(chunks):
        got = dec.feed(RawPacket(1_000 + k, c))
        assert isinstance(got, list)
        out += got
    return out + dec.finish()


def check_common(dec, chunks: list[bytes], out: list) -> None:
    c = dec.counters
    assert c["decoder_errors"] == 0, dec.events
    assert c["packets"] == len(chunks) and c["bytes"] == sum(map(len, chunks)) and c["samples"] == len(out)
    assert len(dec.events) <= EVENT_BOUND
    assert not any(e.kind == "decoder-error" for e in dec.events)
    for s in out:
        assert isinstance(s, ImuSample)
        for v in (s.orientation, s.acceleration, s.rate_of_turn, s.magnetic_field):
            assert v.shape in ((3,), (4,)) and (np.isfinite(v).all() or np.isnan(v).all())
        if np.isfinite(s.orientation).all():
            assert abs(np.linalg.norm(s.orientation) - 1) <= QUATERNION_NORM_TOLERANCE + 1e-9


# ------------------------------------------------------------------------------------------ xbus
def xbus_stream(samples, outputs) -> bytes:
    return b"".join(encode_mtdata2(s, outputs) for s in samples)


xbus_outputs = st.permutations(DEFAULT_OUTPUTS).flatmap(lambda p: st.integers(1, len(p)).map(lambda k: p[:k]))


@given(st.data())
def test_xbus_valid_streams_decode_whatever_the_chunking(data):
    samples, outputs = data.draw(imu_samples()), data.draw(xbus_outputs)
    chunks = data.draw(chunked(xbus_stream(samples, outputs)))
    dec = XbusDecoder("imu")
    out = feed_all(dec, chunks)
    check_common(dec, chunks, out)
    assert len(out) == len(samples)
    if 0x1020 in outputs:
        assert [s.counter for s in out] == [s.counter for s in samples]
    c = dec.counters
    assert c["bytes_skipped"] == c["bad_checksum"] == c["bad_quaternion"] == c["bad_vector"] == 0


@given(st.data())
def test_xbus_mutated_streams_and_garbage_never_raise(data):
    samples, outputs = data.draw(imu_samples()), data.draw(xbus_outputs)
    valid = xbus_stream(samples, outputs)
    extra = data.draw(st.sampled_from([b"", encode_message(0x36), encode_message(0x42, b"\x28"),
                                       encode_message(0x36, data.draw(st.binary(max_size=64)))]))  # fmt: skip
    stream = data.draw(st.one_of(mutated(valid + extra), st.binary(max_size=600)))
    chunks = data.draw(chunked(stream))
    dec = XbusDecoder("imu")
    out = feed_all(dec, chunks)
    check_common(dec, chunks, out)
    assert len(out) <= dec.counters["frames"] <= len(stream) // 5  # one sample per frame of >= 5 bytes
    assert dec.parser.pending == 0  # finish() let go of every byte
    for s in out:
        assert s.counter == -1 or 0 <= s.counter <= 0xFFFF


@given(st.binary(min_size=1, max_size=80), st.integers(0, MAX_FRAME_DATA + 1))
def test_xbus_frames_of_any_content_and_claimed_length(payload, claimed):
    # any MTData2 data (records of any ID, size, precision, NaN bits), a checksum-valid frame each
    frame = encode_message(0x36, payload)
    head = bytes([0xFA, 0xFF, 0x36, 0xFF]) + claimed.to_bytes(2, "big")  # an extended length with too few bytes
    chunks = [frame, head + payload, frame]
    dec = XbusDecoder("imu")
    out = feed_all(dec, chunks)
    check_common(dec, chunks, out)
    assert len(out) <= 3


# ------------------------------------------------------------------------------------------- CAN
def can_packets(samples) -> list[bytes]:
    return [pack_can_frame(m) for s in samples for m in encode_can(s)]


@given(st.data())
def test_can_valid_streams_decode(data):
    samples = data.draw(imu_samples(4))
    chunks = can_packets(samples)
    dec = MtiCanDecoder("imu")
    out = feed_all(dec, chunks)
    check_common(dec, chunks, out)
    assert [s.counter for s in out] == [s.counter for s in samples]
    assert dec.counters["incomplete"] == dec.counters["bad_quaternion"] == 0


can_frames = st.one_of(
    st.binary(min_size=16, max_size=16),  # any can_frame: any flags, length field, data
    st.binary(max_size=24),  # not a can_frame at all
    st.tuples(st.sampled_from([0, 0x20000000, 0x40000000, 0x80000000]), st.integers(0, 0x7FF), st.integers(0, 255),
              st.binary(min_size=8, max_size=8)).map(lambda t: (t[0] | t[1]).to_bytes(4, "little") + bytes([t[2]])
                                                      + bytes(3) + t[3]),  # fmt: skip
)


@given(st.data())
def test_can_arbitrary_and_mutated_frames_never_raise(data):
    valid = can_packets(data.draw(imu_samples(3)))
    frames = data.draw(st.lists(st.one_of(can_frames, st.sampled_from(valid), st.sampled_from(valid).flatmap(mutated)),
                                max_size=60))  # fmt: skip
    dec = MtiCanDecoder("imu")
    out = feed_all(dec, frames)
    check_common(dec, frames, out)
    assert len(out) <= dec.counters["frames"] and len(dec._error_classes) <= 64


# -------------------------------------------------------------------------------------- VIVE USB
hid_slots = st.builds(HidImuSample, st.tuples(*[st.integers(-32768, 32767)] * 3),
                      st.tuples(*[st.integers(-32768, 32767)] * 3), st.integers(0, 2**32 - 1), st.integers(0, 255))


@st.composite
def hid_reports(draw):
    """Mostly a plausible IMU stream (seq and ticks advancing, slots repeated), some arbitrary."""
    seq, ticks, ring, out = draw(st.integers(0, 255)), draw(st.integers(0, 2**32 - 1)), [], []
    for _ in range(draw(st.integers(0, 12))):
        kind = draw(st.sampled_from(["next", "next", "any", "bytes"]))
        if kind == "bytes":
            out.append(draw(st.one_of(st.binary(max_size=60),
                                      st.binary(min_size=REPORT_SIZE - 1, max_size=REPORT_SIZE - 1)
                                      .map(lambda b: bytes([IMU_REPORT_ID]) + b))))  # fmt: skip
            continue
        if kind == "next":
            seq = (seq + draw(st.integers(1, 3))) % 256
            ticks = (ticks + draw(st.integers(0, 2_000_000))) % 2**32
            ring = ([HidImuSample((0, 0, 4096), (1, 2, 3), ticks, seq)] + ring)[:3]
        slots = ring if len(ring) == 3 and kind == "next" else [draw(hid_slots) for _ in range(3)]
        out.append(encode_imu_report(slots))
    return out


@given(hid_reports())
def test_vive_usb_reports_never_raise(reports):
    dec = ViveUsbDecoder()
    out = feed_all(dec, reports)
    check_common(dec, reports, out)
    c = dec.counters
    assert len(out) <= 3 * len(reports) and c["lost"] >= 0
    times = [s.device_time_ns for s in out]
    assert times == sorted(times)  # unwrapped: never back
    for s in out:
        assert np.isnan(s.orientation).all() and np.isfinite(s.acceleration).all() and 0 <= s.counter <= 255
        assert all(math.isfinite(x) for x in s.rate_of_turn)

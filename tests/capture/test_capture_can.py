"""mti+can:// — SocketCAN frame packing, the MTi-600 CAN decoder (grouping, scales, loss, wraps),
and the source on python-can's real virtual bus against the simulated MTi."""

from __future__ import annotations

import math
import struct
import uuid

import can
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dualhuman_builder.capture.mti_can import MtiCanDecoder, MtiCanSource
from dualhuman_builder.capture.samples import ImuSample
from dualhuman_builder.capture.sources import RawPacket, SourceError, SourceLost, make_decoder, open_source
from dualhuman_builder.capture.wire.mti_can import (CanFrame, encode_can, free_acceleration_zup, pack_can_frame,
                                                    unpack_can_frame)  # fmt: skip
from dualhuman_builder.conventions import zup_to_yup_points
from dualhuman_builder.sim.devices import CanPlayer, Faults, Packet
from dualhuman_builder.sim.imu import simulate_imu
from dualhuman_builder.sim.studio import CAN_CLOCK
from dualhuman_builder.tracks import SkeletonTrack


def imu_samples(seconds=1.0, rate=100.0, first_counter=0, device="mti-can") -> list[ImuSample]:
    """A simulated MTi (sim/imu.py, the studio's CAN clock) on a turning, bobbing pelvis."""
    t = np.arange(int(seconds * 60) + 2) / 60.0
    q = Rotation.from_rotvec(np.outer(np.sin(2 * np.pi * 0.5 * t), [0.3, 1.0, 0.2])).as_quat()[:, None]
    p = np.stack([0.1 * t, 0.95 + 0.02 * np.sin(6 * t), 0 * t], -1)[:, None]
    ns = np.round(t * 1e9).astype(np.int64)
    track = SkeletonTrack(("Pelvis",), q, p, ns, ns, fps=60.0)
    return list(simulate_imu(track, "Pelvis", rate, seed=2, clock=CAN_CLOCK, device=device,
                             first_counter=first_counter))  # fmt: skip


def assert_same(got: ImuSample, want: ImuSample, device=None):
    """Equal within the int16 quantisation (half a step; the quaternion is normalised)."""
    assert got.device == (device or want.device)
    assert got.counter == want.counter and got.device_time_ns == want.device_time_ns  # whole us on the wire
    np.testing.assert_allclose(got.orientation, want.orientation, atol=2**-15)
    np.testing.assert_allclose(got.acceleration, want.acceleration, atol=2**-9 + 1e-12)
    np.testing.assert_allclose(got.rate_of_turn, want.rate_of_turn, atol=2**-10 + 1e-12)
    np.testing.assert_allclose(got.magnetic_field, want.magnetic_field, atol=2**-11 + 1e-12)
    assert got.status == want.status


def channel() -> str:
    return f"test-{uuid.uuid4().hex[:8]}"


def read_all(src, idle_reads=3) -> list[RawPacket]:
    out, idle = [], 0
    while idle < idle_reads:
        got = src.read(0.05)
        out += got
        idle = 0 if got else idle + 1
    return out


def decode(decoder, packets) -> list[ImuSample]:
    return [s for p in packets for s in decoder.feed(p)] + decoder.finish()


def packets_of(samples) -> list[RawPacket]:
    return [RawPacket(k, pack_can_frame(m)) for k, s in enumerate(samples) for m in encode_can(s)]


# ------------------------------------------------------------------------------------------ frames
def test_can_frame_packing():
    m = can.Message(arbitration_id=0x21, data=b"\x01\x02\x03", is_extended_id=False)
    raw = pack_can_frame(m)
    assert len(raw) == 16 and raw == struct.pack("<IB3x8s", 0x21, 3, b"\x01\x02\x03")
    assert unpack_can_frame(raw) == CanFrame(0x21, False, False, False, 3, b"\x01\x02\x03")
    ext = pack_can_frame(can.Message(arbitration_id=0x1ABCDEF, data=b"\xff" * 8, is_extended_id=True))
    assert struct.unpack_from("<I", ext)[0] == 0x80000000 | 0x1ABCDEF
    assert unpack_can_frame(ext) == CanFrame(0x1ABCDEF, True, False, False, 8, b"\xff" * 8)
    rtr = pack_can_frame(can.Message(arbitration_id=0x05, is_extended_id=False, is_remote_frame=True, dlc=4))
    assert struct.unpack_from("<IB", rtr) == (0x40000000 | 0x05, 4) and unpack_can_frame(rtr).data == b""
    err = pack_can_frame(can.Message(arbitration_id=0x40, is_error_frame=True, data=bytes(8)))
    assert unpack_can_frame(err) == CanFrame(0x40, False, False, True, 8, bytes(8))
    with pytest.raises(ValueError, match="16 bytes"):
        unpack_can_frame(raw[:15])
    with pytest.raises(ValueError, match="length field 9"):
        unpack_can_frame(struct.pack("<IB3x8s", 0x21, 9, b""))
    with pytest.raises(ValueError, match="not a classic CAN frame"):
        pack_can_frame(can.Message(arbitration_id=0x21, data=bytes(12), is_fd=True))


# ------------------------------------------------------------------------------------------ decoder
def test_decoder_round_trip_scales_and_extras():
    samples = imu_samples(0.5)
    d = MtiCanDecoder("imu")
    got = decode(d, packets_of(samples))
    assert len(got) == len(samples) > 40
    for g, s in zip(got, samples):
        assert_same(g, s, device="imu")
        assert g.host_time_ns == samples.index(s)  # the packet that completed the group
    c = d.counters
    assert c["frames"] == 8 * len(samples) and c["samples"] == len(samples) and c["free_acceleration"] == len(samples)
    assert not any(c[k] for k in ("incomplete", "lost", "unknown_id", "bad_length", "orphan_frames"))
    free, t = d.extras["free_acceleration"]
    assert t == samples[-1].device_time_ns
    np.testing.assert_allclose(free, zup_to_yup_points(free_acceleration_zup(samples[-1])), atol=2**-9)
    # Euler and temperature (not written by the encoder) are decoded with their scales
    extra = [Packet(0, can.Message(arbitration_id=0x05, data=struct.pack(">I", 7), is_extended_id=False)),
             Packet(0, can.Message(arbitration_id=0x22, data=struct.pack(">3h", 128, -256, 23040),
                                   is_extended_id=False)),
             Packet(0, can.Message(arbitration_id=0x51, data=struct.pack(">h", 9000), is_extended_id=False))]
    (g,) = decode(d, [RawPacket(1, pack_can_frame(p.data)) for p in extra])
    np.testing.assert_allclose(d.extras["euler"][0], np.radians([1.0, -2.0, 180.0]))
    assert d.extras["temperature"][0] == (9000 / 256,) and d.counters["euler"] == d.counters["temperature"] == 1
    assert g.counter == -1 and np.isnan(g.orientation).all() and d.counters["incomplete"] == 1


def test_unknown_ids_bad_lengths_and_missing_frames():
    samples = imu_samples(0.1)
    pk = packets_of(samples)
    junk = [can.Message(arbitration_id=0x123, data=b"\x00", is_extended_id=False),  # unknown ID
            can.Message(arbitration_id=0x21, data=bytes(6), is_extended_id=False),  # quaternion with DLC 6
            can.Message(arbitration_id=0x21, data=bytes(8), is_extended_id=True),  # extended: not the MTi's
            can.Message(arbitration_id=0x06, is_extended_id=False, is_remote_frame=True, dlc=2),
            can.Message(arbitration_id=0x04, is_error_frame=True, data=bytes(8))]  # fmt: skip
    stream = pk[:3] + [RawPacket(0, pack_can_frame(m)) for m in junk] + pk[3:] + [RawPacket(0, b"short")]
    # sample 2 loses its quaternion (0x21 is the 4th frame) and its rate of turn
    stream = [p for p in stream if p not in (pk[2 * 8 + 3], pk[2 * 8 + 4])]
    d = MtiCanDecoder()
    got = decode(d, stream)
    assert [g.counter for g in got] == [s.counter for s in samples]
    for g, s in zip(got, samples):
        if g.counter != 2:
            assert_same(g, s)
    assert np.isnan(got[2].orientation).all() and np.isnan(got[2].rate_of_turn).all()
    assert np.isfinite(got[2].acceleration).all() and np.isfinite(got[2].magnetic_field).all()
    c = d.counters
    assert (c["unknown_id"], c["bad_length"], c["remote_frames"], c["error_frames"], c["bad_frame"]) == (2, 1, 1, 1, 1)
    assert c["incomplete"] == 1 and c["lost"] == 0
    (event,) = d.pop_events()
    assert event.kind == "bus-error" and "0x4" in event.message


def test_flagged_frames_with_a_length_over_8_are_counted_not_raised():
    samples = imu_samples(0.05)[:4]
    pk = packets_of(samples)
    crafted = [RawPacket(0, struct.pack("<IB3x8s", flags | 0x05, dlc, bytes(8)))
               for flags in (0x20000000, 0x40000000, 0x80000000, 0xE0000000, 0) for dlc in (9, 15, 255)]  # fmt: skip
    d = MtiCanDecoder()
    got = decode(d, pk[:8] + crafted + pk[8:])
    assert [g.counter for g in got] == [s.counter for s in samples]
    c = d.counters
    assert c["bad_frame"] == len(crafted) and c["error_frames"] == 0 and c["packets"] == len(pk) + len(crafted)
    assert c["decoder_errors"] == 0 and c["incomplete"] == 0


def test_error_frames_of_many_classes_keep_the_decoder_small():
    from dualhuman_builder.capture.mti_can import MAX_ERROR_CLASSES

    d = MtiCanDecoder()
    for k in range(1, 2001):  # every error class different (a crafted take)
        d.feed(RawPacket(k, struct.pack("<IB3x8s", 0x20000000 | k, 8, bytes(8))))
    assert d.counters["error_frames"] == 2000
    assert len(d._error_classes) == MAX_ERROR_CLASSES and len(d.pop_events()) <= MAX_ERROR_CLASSES


def test_sample_time_and_group_counter_wrap():
    base = imu_samples(0.5, first_counter=65520)
    shift = (2**32 - 120_000) * 1000 - base[0].device_time_ns  # the u32 microseconds wrap after 12 samples
    samples = [ImuSample(s.device, s.counter, s.device_time_ns + shift, s.host_time_ns, s.orientation, s.acceleration,
                         s.rate_of_turn, s.magnetic_field) for s in base]  # fmt: skip
    d = MtiCanDecoder("mti-can")
    got = decode(d, packets_of(samples))
    assert [g.device_time_ns for g in got] == [s.device_time_ns for s in samples]  # unwrapped past 2**32 us
    assert got[-1].device_time_ns > 2**32 * 1000 > got[0].device_time_ns
    assert [g.counter for g in got] == [(65520 + k) % 65536 for k in range(len(samples))]
    assert d.counters["lost"] == d.counters["duplicate"] == d.counters["out_of_order"] == 0


# ------------------------------------------------------------------------------------------ bus
def test_round_trip_on_the_virtual_bus():
    samples = imu_samples(1.0)
    ch = channel()
    with open_source(f"mti+can://virtual/{ch}?device=mti-can") as src, \
            can.Bus(interface="virtual", channel=ch) as tx:  # fmt: skip
        report = CanPlayer(tx, speed=math.inf).add_samples(samples).play()
        packets = read_all(src)
        got = decode(src.decoder, packets)
    assert report.sent == 8 * len(samples) == len(packets) and all(len(p.data) == 16 for p in packets)
    assert len(got) == len(samples) > 90
    for g, s in zip(got, samples):
        assert_same(g, s)
    host = [g.host_time_ns for g in got]
    assert host == sorted(host) and set(host) <= {p.host_time_ns for p in packets}
    stats = src.stats()
    assert stats["frames"] == stats["packets"] == len(packets) and stats["samples"] == len(samples)
    assert src.decoder.status(host[-1])["mti-can"] == {"last_ns": host[-1], "live": True}


def test_duplicated_frames_are_counted_and_ignored():
    samples = imu_samples(1.0)
    ch = channel()
    with MtiCanSource(f"mti+can://virtual/{ch}") as src, can.Bus(interface="virtual", channel=ch) as tx:
        report = CanPlayer(tx, speed=math.inf, faults=Faults(seed=4, duplicate=0.1)).add_samples(samples).play()
        got = decode(src.decoder, read_all(src))
    assert len(report.faults.duplicated) > 40
    assert src.decoder.counters["duplicate_frame"] == len(report.faults.duplicated)
    assert len(got) == len(samples) and src.decoder.counters["incomplete"] == 0
    for g, s in zip(got, samples):
        assert_same(g, s, device=ch)  # default device name: the channel


def test_lost_frames_leave_nan_or_lose_the_sample():
    samples = imu_samples(1.0)
    ch = channel()
    with MtiCanSource(f"mti+can://virtual/{ch}?device=imu") as src, can.Bus(interface="virtual", channel=ch) as tx:
        player = CanPlayer(tx, speed=math.inf, faults=Faults(seed=2, loss=0.04)).add_samples(samples)
        report = player.play()
        got = decode(src.decoder, read_all(src))
    lost_ids: dict[int, set[int]] = {}  # sample index -> CAN ids lost
    for i in report.faults.lost:
        lost_ids.setdefault(i // 8, set()).add(player.packets[i].data.arbitration_id)
    # (this seed never loses a GroupCounter right before a lost SampleTime: such a sample would be
    # glued to the previous one, which the decoder cannot tell apart)
    assert not any(0x06 in lost_ids.get(k, ()) and 0x05 in lost_ids.get(k + 1, ()) for k in lost_ids)
    untimed = {k for k, ids in lost_ids.items() if 0x05 in ids}
    kept = [k for k in range(len(samples)) if k not in untimed]
    assert len(untimed) >= 2 and len(lost_ids) > 10
    assert [g.device_time_ns for g in got] == [samples[k].device_time_ns for k in kept]
    nan_field = {0x21: "orientation", 0x32: "rate_of_turn", 0x34: "acceleration", 0x41: "magnetic_field"}
    for g, k in zip(got, kept):
        ids = lost_ids.get(k, set())
        assert g.counter == (-1 if 0x06 in ids else samples[k].counter)
        assert g.status == (0 if 0x11 in ids else samples[k].status)
        for cid, field in nan_field.items():
            assert np.isnan(getattr(g, field)).all() == (cid in ids)
    c = src.decoder.counters
    incomplete = [k for k in kept if lost_ids.get(k, set()) & {0x06, 0x11, 0x21, 0x32, 0x34, 0x41}]
    no_counter = {k for k in kept if 0x06 in lost_ids.get(k, set())}
    assert c["incomplete"] == len(incomplete)
    seen = [k for k in kept if k not in no_counter]
    assert c["lost"] == sum(seen[0] < k < seen[-1] for k in untimed | no_counter)  # counter values never seen
    assert c["orphan_frames"] == sum(8 - len(lost_ids[k]) for k in untimed)


def test_bus_shutdown_is_source_lost_and_close_is_a_clean_end():
    ch = channel()
    with can.Bus(interface="virtual", channel=ch) as tx:
        bus = can.Bus(interface="virtual", channel=ch)
        src = MtiCanSource(f"mti+can://virtual/{ch}", bus=bus)
        for m in encode_can(imu_samples(0.05)[0]):
            tx.send(m)
        assert len(src.read(0.1)) == 8
        bus.shutdown()  # the bus goes down under the source
        with pytest.raises(SourceLost, match=f"CAN bus virtual/{ch} failed while reading"):
            src.read(0.05)
        src.close()
        assert src.read(0.05) == []
        own = MtiCanSource(f"mti+can://virtual/{ch}")
        own.close()  # its own bus is shut down: later reads end cleanly
        assert own.read(0.05) == [] and own.bus._is_shutdown


def test_urls_and_open_errors():
    assert make_decoder("mti+can://socketcan/can0").device == "can0"
    assert make_decoder("mti+can://slcan//dev/ttyACM0?device=floor").device == "floor"
    for url, match, fix in (("mti+can://socketcan", "does not name a CAN interface and channel", "INTERFACE/CHANNEL"),
                            ("mti+can://virtual/x?rate=5", "unknown mti\\+can:// parameter", "device, bitrate"),
                            ("mti+can://virtual/x?bitrate=-1", "bitrate=-1", "bits/s"),
                            ("mti+can://nosuchcan/x", "cannot open CAN nosuchcan/x", "socketcan"),
                            ("mti+can://socketcan/nocan9", "cannot open CAN socketcan/nocan9",
                             "ip link set nocan9 up type can bitrate 1000000")):  # fmt: skip
        with pytest.raises(SourceError, match=match) as e:
            open_source(url)
        assert fix in str(e.value)


"""The recorder and replay on real transports: simulated trackers on UDP loopback recorded into a
take, read back bit for bit, re-decoded, put back on the wire; a full disk and kill -9 mid-take;
transport events in the take; one source lost, one source's decoding failing, the decoding
process killed — the rest of the take goes on."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from dualhuman_builder.capture.log.reader import check_take
from dualhuman_builder.capture.log.repair import repair_take
from dualhuman_builder.capture.recorder import Recorder
from dualhuman_builder.capture.replay import (redecode, replay_packets, replay_samples, replay_to, same_sample,
                                              verify_replay)  # fmt: skip
from dualhuman_builder.capture.sources import open_source
from dualhuman_builder.rig import RigActor
from dualhuman_builder.sim.devices import Faults, UdpPlayer, tracker_packets

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests" / "capture"))

from test_capture_vive import twelve_trackers  # noqa: E402
from test_capture_xbus import imu_samples  # noqa: E402


def record_trackers(path: Path, *, faults=None, speed=20.0, duration_s=0.6, flush_s=0.2, decode="process"):
    stream = twelve_trackers(duration_s=duration_s)
    src = open_source("vive+udp://127.0.0.1:0")
    player = UdpPlayer(("127.0.0.1", src.port), speed=speed, faults=faults).add(tracker_packets(stream, clock="host"))
    actors = [RigActor("alice", None, None, {s: "Pelvis" for s in list(stream.serials)[:6]})]
    rec = Recorder(path, take="T1", sources=[("trackers", src)], actors=actors, flush_s=flush_s, decode=decode)
    player.start()
    statuses = []
    done_at = []

    def until():
        if player.running:
            return False
        done_at.append(time.monotonic())
        return time.monotonic() - done_at[0] > 0.3

    result = rec.run(until=until, on_status=statuses.append, status_every=0.05)
    report = player.join()
    rec.close()
    return result, report, statuses, stream


@pytest.mark.slow
def test_record_replay_bit_identical_and_back_on_the_wire(tmp_path):
    path = tmp_path / "T1.mcap"
    result, report, statuses, stream = record_trackers(path)
    assert result.ok and result.reason == "finished"
    assert report.sent == report.packets
    samples = [s for _, s in replay_samples(path)]
    assert len(samples) == report.sent, "every datagram sent is a recorded sample (zero loss on loopback)"
    packets = [p for _, p in replay_packets(path)]
    assert [p.data for p in packets] == [player_p.data for player_p in sorted(
        tracker_packets(stream, clock="host"), key=lambda p: p.time_ns)]  # fmt: skip
    assert all(a.host_time_ns == p.host_time_ns for a, p in zip(samples, packets))
    # re-decoding the raw bytes gives the recorded samples bit for bit
    chk = verify_replay(path)
    assert chk.identical and chk.samples == len(samples)
    assert all(same_sample(a, b) for (_, a), (_, b) in zip(replay_samples(path), redecode(path)))
    assert statuses and statuses[-1].sources[0].kind == "vive"
    assert statuses[-1].sources[0].samples == len(samples)
    assert check_take(path).ok
    # back on the wire: a second source receives the same datagrams
    sink = open_source("vive+udp://127.0.0.1:0")
    rep = replay_to(path, [f"vive+udp://127.0.0.1:{sink.port}"], speed=math.inf)
    got = []
    deadline = time.monotonic() + 2
    while len(got) < rep.packets and time.monotonic() < deadline:
        got += sink.read(0.05)
    sink.close()
    assert rep.packets == len(packets) and [p.data for p in got] == [p.data for p in packets]


def test_inline_decoding_gives_the_same_take_and_a_live_status(tmp_path):
    """decode="inline" (no decoding process): the same samples, and the live status sees the
    actor's trackers while they stream."""
    a, b = tmp_path / "a.mcap", tmp_path / "b.mcap"
    result, report, statuses, _ = record_trackers(a, decode="inline", speed=2.0)
    record_trackers(b, decode="process", speed=2.0)
    assert result.ok and result.source_stats["trackers"]["samples"] == report.sent
    assert max(s.actors[0].trackers_live for s in statuses) == 6
    for (_, x), (_, y) in zip(replay_samples(a), replay_samples(b), strict=True):
        assert type(x) is type(y) and x.serial == y.serial and x.device_time_ns == y.device_time_ns
        np.testing.assert_array_equal(x.position, y.position)


def test_replay_at_recorded_timing(tmp_path):
    path = tmp_path / "T1.mcap"
    record_trackers(path, speed=4.0, duration_s=0.4)
    packets = [p for _, p in replay_packets(path)]
    recorded = (packets[-1].host_time_ns - packets[0].host_time_ns) / 1e9
    sink = open_source("vive+udp://127.0.0.1:0")
    t = time.perf_counter()
    rep = replay_to(path, [f"vive+udp://127.0.0.1:{sink.port}"], speed=1.0)
    elapsed = time.perf_counter() - t
    sink.close()
    assert rep.recorded_s == pytest.approx(recorded)
    assert elapsed >= 0.95 * recorded  # paced, not dumped


@pytest.mark.slow
def test_faults_are_counted_and_recorded(tmp_path):
    path = tmp_path / "T1.mcap"
    result, report, _, _ = record_trackers(path, faults=Faults(seed=3, loss=0.05, duplicate=0.05))
    st = result.source_stats["trackers"]
    log = report.faults
    assert st["duplicate"] == len(log.duplicated) > 0
    assert st["packets"] == report.sent
    assert st["samples"] == report.sent - len(log.duplicated)
    path = tmp_path / "T2.mcap"
    result, report, _, _ = record_trackers(path, faults=Faults(seed=4, corrupt=0.05))
    st = result.source_stats["trackers"]
    samples = [s for _, s in replay_samples(path)]
    assert len(samples) == st["samples"]
    assert len(list(replay_packets(path))) == report.sent, "damaged datagrams are recorded raw too"


_DISK_FULL = textwrap.dedent("""
    import resource, signal, sys
    sys.path.insert(0, {tests!r})
    from pathlib import Path
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (250_000, 250_000))
    from test_capture_recorder import record_trackers
    result, report, _, _ = record_trackers(Path({path!r}), speed=5.0, duration_s=1.0, flush_s=0.02)
    print("RESULT", result.reason, "|", result.error, flush=True)
""")


@pytest.mark.slow
def test_disk_full_mid_take_stops_cleanly_and_keeps_the_data(tmp_path):
    path = tmp_path / "full.mcap"
    out = subprocess.run([sys.executable, "-c", _DISK_FULL.format(tests=str(ROOT / "tests" / "capture"), path=str(path))],
                         capture_output=True, text=True, timeout=300, cwd=ROOT)  # fmt: skip
    line = [ln for ln in out.stdout.splitlines() if ln.startswith("RESULT")]
    assert line, out.stderr[-3000:]
    assert "write-failed" in line[0] and "file-size limit" in line[0]
    rep = check_take(path)
    assert rep.messages > 0 and not rep.complete
    fixed = repair_take(path, tmp_path / "fixed.mcap")
    assert fixed.messages == rep.messages
    assert check_take(tmp_path / "fixed.mcap").ok


def _orphans(parent_pid: int) -> list[int]:
    """Processes started from the killed recorder (its decoding process) that are still running."""
    out = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                environ = (d / "cmdline").read_bytes()
                if b"multiprocessing.spawn" in environ and f"DUALHUMAN_TEST_PARENT={parent_pid}".encode() in \
                        (d / "environ").read_bytes():  # fmt: skip
                    out.append(int(d.name))
            except OSError:
                continue
    return out


@pytest.mark.slow
def test_kill_minus_9_of_the_capture_command_leaves_a_readable_take(tmp_path):
    """`dualhuman capture` recording a sender that never stops is killed with SIGKILL; the take
    holds everything up to its last flushed chunk and repairs to a complete file."""
    path = tmp_path / "K.mcap"
    sink_port = 47_000 + os.getpid() % 1000
    marker = f"DUALHUMAN_TEST_PARENT={os.getpid()}"
    proc = subprocess.Popen([sys.executable, "-m", "cli", "capture", "--source", f"trk=vive+udp://127.0.0.1:{sink_port}",
                             "--take", "K", "--out", str(path), "--quiet"], cwd=ROOT,
                            env={**os.environ, "DUALHUMAN_TEST_PARENT": str(os.getpid())},
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)  # fmt: skip
    stream = twelve_trackers(duration_s=0.6)
    packets = sorted(tracker_packets(stream, clock="host"), key=lambda p: p.time_ns)
    import socket

    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        deadline = time.monotonic() + 60
        while not path.exists() and time.monotonic() < deadline:
            time.sleep(0.05)
        sent = 0
        t_end = time.monotonic() + 2.5
        while time.monotonic() < t_end:
            for p in packets[:50]:
                tx.sendto(p.data, ("127.0.0.1", sink_port))
                sent += 1
            time.sleep(0.01)
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        tx.close()
    rep = check_take(path)
    assert not rep.complete
    assert rep.per_topic["raw/trk"] > 0.3 * sent, "the flushed chunks (one per second) survive the kill"
    # the recorder's decoding process does not outlive it
    deadline = time.monotonic() + 5
    while _orphans(os.getpid()) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _orphans(os.getpid()), f"a decoding process ({marker}) outlived the killed recorder"
    repair_take(path)
    assert check_take(path).ok


@pytest.mark.slow
def test_cli_capture_into_a_workspace_then_replay_and_dump(tmp_path):
    """`dualhuman capture --source ... -w WS` records, registers the take with its checksum and
    counts; `replay --verify` and `log dump --jsonl` read it back."""
    import json
    import socket
    import threading

    from click.testing import CliRunner

    from dualhuman_builder.cli import main
    from dualhuman_builder.workspace import Workspace
    from dualhuman_builder.fileio import sha256_file

    ws_path = tmp_path / "ws"
    runner = CliRunner()
    assert runner.invoke(main, ["init", str(ws_path)]).exit_code == 0
    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    stream = twelve_trackers(duration_s=0.4)
    player = UdpPlayer(("127.0.0.1", port), speed=1.0).add(tracker_packets(stream, clock="host"))
    threading.Timer(0.5, player.start).start()
    r = runner.invoke(main, ["capture", "--source", f"trk=vive+udp://127.0.0.1:{port}", "--actor", "alice=trk#0",
                             "--take", "T9", "--duration", "2.0", "-w", str(ws_path), "--quiet"])  # fmt: skip
    assert r.exit_code == 0, r.output
    report = player.join()
    assert "take T9" in r.output and f"samples {report.sent}" in r.output
    take_file = ws_path / "takes" / "T9" / "T9.mcap"
    with Workspace.open(ws_path) as ws:
        take = ws.take("T9")
        assert take.files[0]["sha256"] == sha256_file(take_file)
        assert sum(take.sample_counts.values()) == report.sent
        assert take.meta["reason"] == "duration" and take.meta["unregistered_actors"] == ["alice"]
    r = runner.invoke(main, ["replay", str(take_file), "--verify"])
    assert r.exit_code == 0 and "bit for bit" in r.output
    r = runner.invoke(main, ["log", "dump", str(take_file), "--jsonl"])
    rows = [json.loads(line) for line in r.output.splitlines()]
    assert len(rows) == report.sent and {row["type"] for row in rows} == {"TrackerSample"}
    r = runner.invoke(main, ["capture", "--source", "trk=vive+udp://127.0.0.1:1", "--take", "T9", "-w", str(ws_path)])
    assert r.exit_code == 2 and "already in the workspace" in r.output


# ------------------------------------------------------------------ events and failures mid-take
def take_events_and_stats(path: Path) -> tuple[list[dict], dict]:
    """The ``events`` messages of a take file, and its final ``stats`` metadata (JSON decoded)."""
    import json

    from dualhuman_builder.capture.log.reader import TakeReader

    r = TakeReader(path)
    events = [json.loads(bytes(m.data)) for ch, m in r.messages() if ch.topic == "events"]
    stats = {k: json.loads(v) for k, v in r.metadata.get("stats", {}).items()}
    return events, stats


def raw_counts(path: Path) -> dict[str, int]:
    from collections import Counter

    return dict(Counter(name for name, _ in replay_packets(path)))


@pytest.mark.parametrize("decode", ["process", "inline"])
def test_rejected_senders_and_kernel_drops_are_events_of_the_take(tmp_path, decode):
    """A sender on 127.0.0.2 outside allow= and datagrams the kernel dropped (a tiny receive
    buffer flooded before the take starts) are events in the take file and the result, with
    decoding in its own process or inline."""
    import socket

    stray = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stray.bind(("127.0.0.2", 0))
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    src = open_source("vive+udp://127.0.0.1:0?allow=127.0.0.1&rcvbuf=2048")
    data = [p.data for p in tracker_packets(twelve_trackers(duration_s=0.1), clock="host")]
    try:
        assert src.buffer_bytes == src.sock.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF)
        for d in data[:2]:
            stray.sendto(d, ("127.0.0.1", src.port))
        for d in data[:200]:  # far more than a few KiB hold: the kernel drops most
            tx.sendto(d, ("127.0.0.1", src.port))
        path = tmp_path / "E.mcap"
        rec = Recorder(path, take="E", sources=[("trk", src)], decode=decode)
        result = rec.run(duration=0.4)
        rec.close()
    finally:
        stray.close()
        tx.close()
    assert result.ok, result.error
    st = result.source_stats["trk"]
    assert st["rejected_senders"] == 2 and st["kernel_drops"] > 0
    kinds = [(e["source"], e["kind"]) for e in result.events]
    assert ("trk", "rejected-sender") in kinds and ("trk", "kernel-drops") in kinds
    events, _ = take_events_and_stats(path)
    rejected = [e for e in events if e["kind"] == "rejected-sender"]
    assert len(rejected) == 1 and "127.0.0.2" in rejected[0]["message"]
    (drops,) = [e for e in events if e["kind"] == "kernel-drops"]
    assert f"total {st['kernel_drops']}" in drops["message"] and "rcvbuf" in drops["message"]


def test_rcvbuf_out_of_range_is_a_clear_error():
    from dualhuman_builder.capture.sources import SourceError

    for bad in ("0", "-5", str(1 << 40)):
        with pytest.raises(SourceError, match="rcvbuf=.* out of range"):
            open_source(f"vive+udp://127.0.0.1:0?rcvbuf={bad}")


def test_a_lost_device_ends_its_source_and_the_others_record_on(tmp_path):
    """An Xbus MTi on a pty whose other end closes mid-take (unplugged): that source ends with a
    source-lost event and its data so far kept; the trackers record to the end."""
    import threading

    from dualhuman_builder.capture.wire.xbus import encode_mtdata2
    from dualhuman_builder.sim.devices import PtyMaster

    pty = PtyMaster()
    xbus = open_source(f"xbus://{pty.slave_path}?config=0&device=prop")
    trk = open_source("vive+udp://127.0.0.1:0")
    stream = twelve_trackers(duration_s=0.5)
    player = UdpPlayer(("127.0.0.1", trk.port), speed=1.0).add(tracker_packets(stream, clock="host"))
    frames = [encode_mtdata2(s) for s in imu_samples(0.05)]
    path = tmp_path / "L.mcap"
    rec = Recorder(path, take="L", sources=[("trackers", trk), ("prop", xbus)])
    for f in frames:
        pty.write(f)
    unplug = threading.Timer(0.2, pty.close)
    player.start()
    unplug.start()
    done_at = []

    def until():
        if player.running:
            return False
        done_at.append(time.monotonic())
        return time.monotonic() - done_at[0] > 0.3

    result = rec.run(until=until, duration=20)
    report = player.join()
    unplug.join()
    rec.close()
    assert result.reason == "finished" and list(result.ended) == ["prop"]
    assert "failed while reading" in result.ended["prop"]
    assert "'prop'" in result.error and "was lost" in result.error and "reconnect" in result.fix
    assert result.source_stats["trackers"]["samples"] == report.sent, "the trackers were recorded to the end"
    assert result.source_stats["prop"]["samples"] == len(frames), "what came before the loss is kept"
    assert raw_counts(path)["trackers"] == report.sent
    events, stats = take_events_and_stats(path)
    (lost,) = [e for e in events if e["kind"] == "source-lost"]
    assert lost["source"] == "prop" and "1 other source(s) go on recording" in lost["message"]
    assert list(stats["ended_sources"]) == ["prop"] and stats["reason"] == "finished"
    assert check_take(path).ok


def test_the_take_stops_when_every_source_is_lost(tmp_path):
    from dualhuman_builder.sim.devices import PtyMaster

    pty = PtyMaster()
    xbus = open_source(f"xbus://{pty.slave_path}?config=0")
    rec = Recorder(tmp_path / "A.mcap", take="A", sources=[("prop", xbus)], decode="inline")
    pty.close()
    result = rec.run(duration=30)
    rec.close()
    assert result.reason == "source-lost" and result.duration_s < 10
    assert result.error.startswith("every source was lost") and list(result.ended) == ["prop"]


def test_a_killed_decoding_process_leaves_raw_recording_going(tmp_path):
    """The decoding process killed mid-take (as the OOM killer would): every raw packet is still
    recorded to the end, the result and the take say decoding failed and how to recover."""
    path = tmp_path / "K.mcap"
    src = open_source("vive+udp://127.0.0.1:0")
    stream = twelve_trackers(duration_s=0.8)
    player = UdpPlayer(("127.0.0.1", src.port), speed=1.0).add(tracker_packets(stream, clock="host"))
    rec = Recorder(path, take="K", sources=[("trackers", src)], flush_s=0.2)
    statuses = []
    player.start()
    t0 = time.monotonic()
    done_at = []

    def until():
        if rec._dproc.proc.is_alive() and time.monotonic() - t0 > 0.3:
            os.kill(rec._dproc.proc.pid, signal.SIGKILL)
        if player.running:
            return False
        done_at.append(time.monotonic())
        return time.monotonic() - done_at[0] > 0.3

    result = rec.run(until=until, on_status=statuses.append, duration=20)
    report = player.join()
    rec.close()
    assert result.reason == "finished"
    assert set(result.decode_failed) == {"*"} and "signal 9" in result.decode_failed["*"]
    assert "decoding failed" in result.error and "log repair" in result.fix
    assert raw_counts(path)["trackers"] == report.sent, "every raw packet was recorded after decoding stopped"
    assert sum(result.samples_per_topic.values()) < report.sent
    assert statuses[-1].sources[0].state == "raw only"
    events, stats = take_events_and_stats(path)
    (failed,) = [e for e in events if e["kind"] == "decoding-failed"]
    assert failed["source"] == "*" and "log repair" in failed["message"]
    assert stats["decode_failed"] == result.decode_failed and "log repair" in stats["fix"]
    assert check_take(path).ok
    fixed = tmp_path / "K-repaired.mcap"  # the recovery the fix names: every sample re-decoded from the raw packets
    repair_take(path, fixed)
    assert sum(1 for _ in replay_samples(fixed)) == report.sent


class _Unwritable:
    """What a broken decoder returns: not a sample the take can hold."""

    host_time_ns = 0


def _broken_source_class():
    from dualhuman_builder.capture.vive_udp import ViveUdpDecoder, ViveUdpSource

    class BrokenDecoder(ViveUdpDecoder):
        def feed(self, packet):
            return [_Unwritable()] if packet.data.startswith(b"BAD") else super().feed(packet)

    class BrokenSource(ViveUdpSource):
        @classmethod
        def make_decoder(cls, url):
            return BrokenDecoder()

    return BrokenSource


def test_one_source_failing_to_decode_leaves_the_others_decoded(tmp_path):
    """Inline decoding: one source's samples cannot be written (its decoder returns what no take
    holds); its decoding ends with an event, its raw packets are still recorded, the other source
    is decoded to the end."""
    import socket

    good = open_source("vive+udp://127.0.0.1:0")
    bad = _broken_source_class()("vive+udp://127.0.0.1:0")
    stream = twelve_trackers(duration_s=0.3)
    packets = tracker_packets(stream, clock="host")
    path = tmp_path / "B.mcap"
    rec = Recorder(path, take="B", sources=[("good", good), ("bad", bad)], decode="inline")
    p1 = UdpPlayer(("127.0.0.1", good.port), speed=2.0).add(packets)
    p2 = UdpPlayer(("127.0.0.1", bad.port), speed=2.0).add(packets)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    p1.start()
    p2.start()
    tx.sendto(b"BAD datagram", ("127.0.0.1", bad.port))
    tx.close()
    done_at = []

    def until():
        if p1.running or p2.running:
            return False
        done_at.append(time.monotonic())
        return time.monotonic() - done_at[0] > 0.3

    result = rec.run(until=until, duration=20)
    sent = p1.join().sent
    p2.join()
    rec.close()
    assert result.reason == "finished" and list(result.decode_failed) == ["bad"]
    assert "decoding source 'bad' failed" in result.error and "log repair" in result.fix
    assert result.source_stats["good"]["samples"] == sent
    assert raw_counts(path) == {"good": sent, "bad": sent + 1}
    events, stats = take_events_and_stats(path)
    (failed,) = [e for e in events if e["kind"] == "decoding-failed"]
    assert failed["source"] == "bad" and list(stats["decode_failed"]) == ["bad"]

"""The simulated studio end to end: sim:// sources, playing every device onto real loopback
transports, and the scene and sim commands."""

from __future__ import annotations

import json
import math
import socket
import struct

import numpy as np
import pytest
from click.testing import CliRunner

from dualhuman_builder import cli
from dualhuman_builder.capture.samples import ImuSample, SuitFrame, TrackerSample
from dualhuman_builder.capture.sources import SourceError, open_source

URL = "sim://high_five?seed=0&fps=15"


@pytest.fixture(scope="module")
def source():
    with open_source(URL) as src:
        yield src


def test_sim_source_yields_every_device_in_arrival_order(source):
    samples = list(source)
    host = np.array([s.host_time_ns for s in samples])
    assert (np.diff(host) >= 0).all()
    duration = source.scene.sequence.num_frames / source.scene.sequence.fps
    suits = [s for s in samples if isinstance(s, SuitFrame)]
    trackers = [s for s in samples if isinstance(s, TrackerSample)]
    imus = [s for s in samples if isinstance(s, ImuSample)]
    assert {s.character for s in suits} == {0, 1}
    for c in (0, 1):  # 240 Hz per suit over the scene
        n = sum(s.character == c for s in suits)
        assert n == pytest.approx(240 * duration, rel=0.03)
        assert all(len(s.segment_names) == 23 for s in suits[:5])
    serials = {s.serial for s in trackers}
    assert len(serials) == 12 and "SIM-A-PELVIS" in serials and "SIM-B-RFOOT" in serials  # rigs/sim.toml
    assert len(trackers) == pytest.approx(12 * 250 * duration, rel=0.03)
    by_dev = {d: sum(s.device == d for s in imus) for d in ("mti-xbus", "mti-can")}
    assert by_dev["mti-xbus"] == pytest.approx(400 * duration, rel=0.03)
    assert by_dev["mti-can"] == pytest.approx(100 * duration, rel=0.03)
    # the suit of actor 0 follows the ground truth: its pelvis starts near actor 0's root
    root0 = np.array(source.scene.sequence.actors[0].transl[0])
    first = next(s for s in suits if s.character == 0)
    assert np.linalg.norm(first.positions[0] - root0) < 0.15


def test_sim_source_errors_and_scene_files(tmp_path, source):
    for url, match in (("sim://waltz?seed=1", "unknown scene type"), ("sim://handshake?sed=1", "unknown sim:// parameter"),
                       ("sim://handshake?seed=x", "not an int"), ("sim:///nope/scene.npz", "no scene file"),
                       ("mvn+udp://127.0.0.1:99999", "bad port"), ("sim://handshake?duration=1", "too short"), ("ftp://x", "unknown source scheme"),
                       ("sim://handshake?preset=noisy", "unknown device error preset")):  # fmt: skip
        with pytest.raises(SourceError, match=match):
            open_source(url)
    path = source.scene.save(tmp_path / "scene.npz")
    with open_source(f"sim://{path}?devices=5") as src:
        assert src.scene.params == source.scene.params
        assert src.studio.counts() == source.studio.counts()
        # another device seed: other noise on the same motion
        a = next(iter(src.studio.suits[0])).orientations
        b = next(iter(source.studio.suits[0])).orientations
        assert not np.allclose(a, b)


def _udp_sink():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 8 << 20)
    sock.bind(("127.0.0.1", 0))
    sock.settimeout(0.5)
    return sock


def _drain(sock) -> list[bytes]:
    out = []
    try:
        while True:
            out.append(sock.recv(65536))
    except socket.timeout:
        return out


def test_play_studio_onto_loopback_udp_and_virtual_can(source):
    import can

    from dualhuman_builder.sim.devices import Faults
    from dualhuman_builder.sim.play import play_studio

    mvn, vive = _udp_sink(), _udp_sink()
    listener = can.Bus(interface="virtual", channel="dualhuman-test-studio")
    try:
        play = play_studio(source.studio, mvn=f"127.0.0.1:{mvn.getsockname()[1]}",
                           trackers=f"127.0.0.1:{vive.getsockname()[1]}", can_bus="virtual:dualhuman-test-studio",
                           speed=8.0, faults=Faults(seed=1, loss=0.05))  # fmt: skip
        with play:
            reports = play.join(timeout=60)
            got_mvn, got_vive = _drain(mvn), _drain(vive)
        frames = []
        while (m := listener.recv(timeout=0.05)) is not None:
            frames.append(m)
    finally:
        mvn.close(), vive.close(), listener.shutdown()
    assert all(r.completed for r in reports.values())
    # every datagram the player sent arrived (loopback), and the 5 % loss is really missing
    assert len(got_mvn) == reports["mvn"].sent
    assert reports["mvn"].packets * 0.9 < reports["mvn"].sent < reports["mvn"].packets * 0.99
    assert all(d[:4] == b"MXTP" for d in got_mvn)
    types = {d[4:6] for d in got_mvn}  # the MVN spec: 'MXTP' + two digits of the type, 24-byte header
    assert {b"02", b"25"} <= types
    characters = {d[16] for d in got_mvn if d[4:6] == b"02"}  # header byte 16: character ID
    assert characters == {0, 1}
    assert len(got_vive) == reports["trackers"].sent
    assert len(frames) == reports["can"].sent > 0
    assert reports["mvn"].faults.counts()["lost"] == reports["mvn"].packets - reports["mvn"].sent


def test_scene_and_sim_commands(tmp_path):
    from PIL import Image

    run = lambda *a: CliRunner().invoke(cli.main, [str(x) for x in a])  # noqa: E731
    out = tmp_path / "hf.npz"
    r = run("scene", "make", "--type", "high_five", "--seed", "0", "--fps", "15", "--out", out)
    assert r.exit_code == 0, r.output
    assert "quality contract: met" in r.output and out.is_file()
    r = run("scene", "info", out, "--json")
    info = json.loads(r.output)
    assert info["params"]["type"] == "high_five" and info["contract_failures"] == []
    assert info["frames"] == round(info["duration_s"] * 15)
    png = tmp_path / "strip.png"
    r = run("scene", "preview", out, "--out", png, "--frames", "2", "--spp", "2")
    assert r.exit_code == 0, r.output
    img = Image.open(png)
    assert img.size == (600, 360)
    px = np.asarray(img.convert("RGB"), dtype=float)
    assert px.std() > 10  # not blank: bodies and floor
    # parameters that cannot work are refused with a clear message
    r = run("scene", "make", "--type", "high_five", "--duration", "0.5", "--out", tmp_path / "x.npz")
    assert r.exit_code == 2 and "too short" in r.output
    r = run("scene", "make", "--heights", "1.7", "--out", tmp_path / "x.npz")
    assert r.exit_code == 2 and "2 comma-separated numbers" in r.output
    # sim play from the saved scene, as fast as possible, to a local UDP sink
    sink = _udp_sink()
    try:
        r = run("sim", "play", f"sim://{out}", "--mvn", f"127.0.0.1:{sink.getsockname()[1]}", "--trackers", "",
                "--speed", "0", "--outage", "0.5-1.0@mvn/1")  # fmt: skip
        got = _drain(sink)
    finally:
        sink.close()
    assert r.exit_code == 0, r.output
    sent = int(r.output.split("mvn: sent ")[1].split()[0])
    assert sent == len(got) > 0 and "outage" in r.output
    r = run("sim", "play", "sim://handshake?seed=0", "--outage", "2-1@mvn/0")
    assert r.exit_code != 0 and "outage" in r.output


def test_mvn_header_layout_read_independently(source):
    """One pose datagram of the studio read with struct per the MVN streaming spec (not our decoder)."""
    from dualhuman_builder.capture.wire.mvn import encode_frame

    frame = next(iter(source.studio.suits[1]))
    pieces = encode_frame(frame, time_code=False)
    items = 0
    for k, d in enumerate(pieces):
        magic, counter, dgram, n_items, time_code, char, n_seg, n_props, n_fingers, _, size = struct.unpack(
            ">6sIBBIBBBBHH", d[:24])
        assert magic == b"MXTP02" and counter == frame.sample_counter and char == 1
        assert time_code == frame.time_code_ms and n_seg == 23 and (n_props, n_fingers) == (0, 0)
        assert dgram & 0x7F == k and bool(dgram & 0x80) == (k == len(pieces) - 1)
        assert size == len(d) - 24 == 32 * n_items
        items += n_items
        seg_id = struct.unpack(">i7f", d[24:56])[0]
        assert 1 <= seg_id <= 23
    assert items == 23 and math.isfinite(frame.positions.sum())


def test_pty_drops_what_nobody_reads_when_asked():
    import os

    from dualhuman_builder.sim.devices import PtyMaster

    with PtyMaster(drop_when_full=True) as pty:
        data = bytes(range(256)) * 800  # 200 KiB, more than a pty buffers
        assert pty.write(data) == len(data)  # returns at once instead of waiting for a reader
        assert 0 < pty.dropped_bytes < len(data)
        fd = os.open(pty.slave_path, os.O_RDONLY | os.O_NONBLOCK)
        got = b""
        try:
            while True:
                got += os.read(fd, 65536)
        except BlockingIOError:
            pass
        finally:
            os.close(fd)
        assert len(got) == len(data) - pty.dropped_bytes and data.startswith(got)
    with PtyMaster(write_timeout=0.2) as pty:  # the default still refuses to lose bytes silently
        with pytest.raises(TimeoutError, match="did not read"):
            pty.write(bytes(200_000))

"""Take files: schemas round trip, writer -> reader, the mcap library reads our files, check /
repair after kill -9 and a full disk, dump as JSON lines."""

from __future__ import annotations

import io
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
from mcap.exceptions import McapError
from mcap.reader import make_reader

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.log import schemas
from dualhuman_builder.capture.log.reader import TakeReader, check_take, dump_jsonl, read_columns, scan_take
from dualhuman_builder.capture.log.repair import repair_take
from dualhuman_builder.capture.log.writer import TakeWriteError, TakeWriter
from dualhuman_builder.capture.samples import ImuSample, SuitFrame, TrackerSample
from dualhuman_builder.capture.replay import same_sample
from dualhuman_builder.capture.sources import RawPacket
from dualhuman_builder.errors import FormatError

ROOT = Path(__file__).resolve().parents[2]


def synthetic_samples(n: int = 200, seed: int = 0) -> list:
    """Interleaved suit frames (2 characters), tracker samples and IMU samples with random values."""
    g = np.random.default_rng(seed)
    out = []
    t0 = 1_000_000_000
    for k in range(n):
        t = t0 + k * 4_166_667
        for c in (0, 1):
            q = g.normal(size=(23, 4))
            out.append(SuitFrame(c, k, k * 4, t, t + 1000 + c, tuple(MVN_SEGMENTS), q / np.linalg.norm(q, axis=1, keepdims=True),
                                 g.normal(size=(23, 3))))  # fmt: skip
        qt = g.normal(size=4)
        out.append(TrackerSample(f"LHR-{k % 3}", bool(k % 7), t - 5, t + 2000, g.normal(size=3), qt / np.linalg.norm(qt),
                                 g.normal(size=3), g.normal(size=3)))  # fmt: skip
        out.append(ImuSample("mti", k & 0xFFFF, t, t + 3000, qt / np.linalg.norm(qt), g.normal(size=3), g.normal(size=3),
                             np.full(3, np.nan) if k % 5 == 0 else g.normal(size=3), status=k))  # fmt: skip
    return out


def write_take(path: Path, samples, **kw) -> TakeWriter:
    w = TakeWriter(path, take="t", sources=[("suits", "mvn+udp://127.0.0.1:9763", "mvn")],
                   bindings={"suits": {"mvn/0": {"actor": "alice"}}, "*": {"vive/LHR-1": {"actor": "alice", "segment": "Head"}}},
                   rig_text="[rig]\nname = 'x'\n", **kw)  # fmt: skip
    for i, s in enumerate(samples):
        w.add_raw(0, RawPacket(s.host_time_ns, bytes([i % 256]) * (i % 50)))
        w.add_sample(0, s)
    return w


def test_schema_round_trip_is_exact_and_definitions_are_ros1():
    for s in synthetic_samples(6):
        layout = schemas.layout_for(s)
        data = schemas.encode(layout, s)
        back = schemas.decode(schemas.parse_definition(layout.schema_name, layout.definition, schemas.sample_classes()), data)
        assert same_sample(s, back)
        assert layout.schema_name == f"dualhuman/{type(s).__name__}"
    frame = synthetic_samples(1)[0]
    d = schemas.layout_for(frame).definition
    assert "int64 character\n" in d and "string[] segment_names\n" in d and "float64[] orientations\n" in d
    assert "uint32[] orientations__shape\n" in d


def test_schema_decode_rejects_lies_without_allocating():
    s = synthetic_samples(1)[2]  # a tracker sample
    layout = schemas.layout_for(s)
    data = bytearray(schemas.encode(layout, s))
    with pytest.raises(FormatError, match="truncated|past the end"):
        schemas.decode(layout, bytes(data[:-5]))
    with pytest.raises(FormatError, match="after its last field"):
        schemas.decode(layout, bytes(data) + b"\0")
    # the position array's count claims 2**31 values: rejected before any allocation
    off = 4 + len("LHR-0") + 1 + 8 + 8
    data[off:off + 4] = (2**31).to_bytes(4, "little")
    with pytest.raises(FormatError, match="past the end"):
        schemas.decode(layout, bytes(data))


def test_writer_reader_round_trip_and_mcap_library_reads_it(tmp_path):
    samples = synthetic_samples(150)
    path = tmp_path / "t.mcap"
    w = write_take(path, samples, chunk_size=16 << 10)
    w.close({"sources": {"suits": {"lost": 0}}})
    back = [s for _, s in TakeReader(path).samples()]
    assert len(back) == len(samples) and all(same_sample(a, b) for a, b in zip(samples, back))
    raw = [p for _, p in TakeReader(path).raw_packets()]
    assert [p.data for p in raw] == [bytes([i % 256]) * (i % 50) for i in range(len(samples))]
    assert [p.host_time_ns for p in raw] == [s.host_time_ns for s in samples]
    # the library's indexed reader: summary, statistics, schemas, metadata
    with open(path, "rb") as f:
        r = make_reader(f)
        summary = r.get_summary()
        assert summary.statistics.message_count == w.messages
        assert summary.statistics.chunk_count > 3
        names = {s.name for s in summary.schemas.values()}
        assert {"dualhuman/SuitFrame", "dualhuman/TrackerSample", "dualhuman/ImuSample", "foxglove.FrameTransforms"} <= names
        meta = {m.name: m.metadata for m in r.iter_metadata()}
        assert meta["rig"]["toml"].startswith("[rig]") and meta["take"]["name"] == "t"
        assert "dualhuman-builder" in meta["software"] and json.loads(meta["stats"]["sources"])["suits"]["lost"] == 0
        topics = {ch.topic: ch for ch in summary.channels.values()}
        assert topics["suits/mvn/0/SuitFrame"].metadata["actor"] == "alice"
        assert topics["suits/vive/LHR-1/TrackerSample"].metadata == {"source": "suits", "entity": "vive/LHR-1", "kind": "mvn",
                                                                     "actor": "alice", "segment": "Head"}  # fmt: skip
        tf = [m for _, ch, m in r.iter_messages(topics=["tf/alice"])]
        assert tf, "Foxglove transforms are written for the bound actor"
        body = json.loads(tf[0].data)
        assert body["transforms"][0]["child_frame_id"] == "studio"
        assert body["transforms"][1]["child_frame_id"] == "alice/Pelvis"
    assert check_take(path).ok


def test_columns_equal_the_samples(tmp_path):
    samples = synthetic_samples(60)
    path = tmp_path / "t.mcap"
    write_take(path, samples).close()
    cols = read_columns(path)
    frames = [s for s in samples if isinstance(s, SuitFrame) and s.character == 1]
    c = cols["suits/mvn/1/SuitFrame"]
    assert c.count == len(frames) and c.sample_type == "SuitFrame"
    np.testing.assert_array_equal(c.columns["orientations"], np.stack([f.orientations for f in frames]))
    np.testing.assert_array_equal(c.columns["host_time_ns"], [f.host_time_ns for f in frames])
    assert c.columns["segment_names"] == tuple(MVN_SEGMENTS)
    imu = cols["suits/imu/mti/ImuSample"]
    np.testing.assert_array_equal(imu.columns["magnetic_field"], np.stack([s.magnetic_field for s in samples if isinstance(s, ImuSample)]))


def test_columns_from_the_index_and_from_a_cut_off_take_agree(tmp_path):
    from dualhuman_builder.capture.samples import SuitTimeCode

    samples = synthetic_samples(300)
    samples += [SuitTimeCode(0, k, k, k, 2_000_000_000 + k, f"00:00:{k // 100:02d}.{k % 1000:03d}", k) for k in range(300)]
    path = tmp_path / "t.mcap"
    write_take(path, samples, chunk_size=32 << 10).close()
    full = read_columns(path)  # through the index
    np.testing.assert_array_equal(full["suits/mvn/0/SuitTimeCode"].columns["text"], [s.text for s in samples[-300:]])
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: int(path.stat().st_size * 0.6)])
    part = read_columns(cut)  # no index: every record scanned
    c_full, c_part = full["suits/vive/LHR-1/TrackerSample"], part["suits/vive/LHR-1/TrackerSample"]
    assert 0 < c_part.count < c_full.count
    np.testing.assert_array_equal(c_part.columns["position"], c_full.columns["position"][: c_part.count])
    assert c_part.columns["serial"] == "LHR-1"


def test_never_overwrites_a_take(tmp_path):
    path = tmp_path / "t.mcap"
    write_take(path, synthetic_samples(2)).close()
    with pytest.raises(TakeWriteError, match="never overwritten"):
        write_take(path, [])


_WRITER_SCRIPT = textwrap.dedent("""
    import sys, time
    sys.path.insert(0, {tests!r})
    from test_take_log import synthetic_samples, write_take
    from pathlib import Path
    samples = synthetic_samples(50)
    w = write_take(Path({path!r}), [], flush_s=0.05, chunk_size=1 << 30)
    k = 0
    while True:
        for s in samples:
            w.add_sample(0, s)
        k += len(samples)
        if w.maybe_flush():
            print("flushed", k, flush=True)
        time.sleep(0.005)
""")


@pytest.mark.slow
def test_kill_minus_9_keeps_every_flushed_chunk_and_repair_rebuilds_the_index(tmp_path):
    path = tmp_path / "crash.mcap"
    script = _WRITER_SCRIPT.format(tests=str(ROOT / "tests" / "capture"), path=str(path))
    proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=ROOT)
    flushed = []
    try:
        while len(flushed) < 4:
            line = proc.stdout.readline()
            assert line, "the writer died before flushing"
            flushed.append(int(line.split()[1]))
    finally:
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
    scan = scan_take(path)
    assert not scan.complete
    rep = check_take(path)
    assert not rep.ok and not rep.complete
    samples_before = sum(n for t, n in rep.per_topic.items() if not t.startswith(("raw/", "tf/")))
    assert samples_before >= flushed[-1], "every sample flushed before the kill is readable"
    with pytest.raises(McapError):  # the library's indexed reader needs the footer the kill prevented
        with open(path, "rb") as f:
            make_reader(f).get_summary().statistics.message_count  # noqa: B018
    fixed = repair_take(path)
    assert fixed.original.exists() and fixed.path == path
    assert check_take(path).ok
    with open(path, "rb") as f:
        r = make_reader(f)
        assert r.get_summary().statistics.message_count == rep.messages
        assert "repair" in {m.name for m in r.iter_metadata()}
    with pytest.raises(FormatError, match="nothing to repair"):
        repair_take(path)


_FULL_DISK_SCRIPT = textwrap.dedent("""
    import resource, signal, sys
    sys.path.insert(0, {tests!r})
    signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (300_000, 300_000))
    from test_take_log import synthetic_samples, write_take
    from dualhuman_builder.capture.log.writer import TakeWriteError
    from pathlib import Path
    samples = synthetic_samples(50)
    w = write_take(Path({path!r}), [], flush_s=0.0, chunk_size=20_000)
    n = 0
    try:
        while True:
            for s in samples:
                w.add_sample(0, s)
                n += 1
            w.maybe_flush()
    except TakeWriteError as e:
        print("stopped", n, e.message, flush=True)
    w.close()
""")


@pytest.mark.slow
def test_a_full_disk_stops_writing_with_a_clear_error_and_keeps_what_was_written(tmp_path):
    path = tmp_path / "full.mcap"
    out = subprocess.run([sys.executable, "-c", _FULL_DISK_SCRIPT.format(tests=str(ROOT / "tests" / "capture"), path=str(path))],
                         capture_output=True, text=True, cwd=ROOT, timeout=120)  # fmt: skip
    assert "stopped" in out.stdout, out.stderr
    assert "file-size limit was reached" in out.stdout
    assert path.stat().st_size <= 300_000
    rep = check_take(path)
    assert rep.messages > 100 and not rep.complete
    assert repair_take(path, tmp_path / "fixed.mcap").messages == rep.messages


def test_damaged_chunk_is_skipped_and_reported(tmp_path):
    path = tmp_path / "t.mcap"
    write_take(path, synthetic_samples(100), chunk_size=8 << 10).close()
    data = bytearray(path.read_bytes())
    mid = len(data) // 2
    data[mid:mid + 64] = bytes(64)  # zero a stretch inside a chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    rep = check_take(bad)
    assert not rep.ok and rep.problems
    assert 0 < rep.messages < check_take(path).messages


def test_not_an_mcap_file(tmp_path):
    p = tmp_path / "x.mcap"
    p.write_bytes(b"hello world, not a take")
    with pytest.raises(FormatError, match="not an MCAP file"):
        check_take(p)


def test_dump_jsonl_has_one_object_per_sample_in_si_units(tmp_path):
    samples = synthetic_samples(5)
    path = tmp_path / "t.mcap"
    write_take(path, samples).close()
    buf = io.StringIO()
    n = dump_jsonl(path, buf)
    rows = [json.loads(line) for line in buf.getvalue().splitlines()]
    assert n == len(rows) == len(samples)
    first = rows[0]
    assert first["type"] == "SuitFrame" and first["actor"] == "alice" and first["entity"] == "mvn/0"
    assert first["host_time_ns"] == samples[0].host_time_ns and len(first["orientations"]) == 23
    assert rows[2]["type"] == "TrackerSample" and rows[2]["serial"] == "LHR-0"
    buf = io.StringIO()
    dump_jsonl(path, buf, raw=True, topics=("raw/",))
    raw = [json.loads(line) for line in buf.getvalue().splitlines()]
    assert len(raw) == len(samples) and raw[1]["data_hex"] == "01"


def test_cli_log_check_repair_dump(tmp_path):
    from click.testing import CliRunner

    from dualhuman_builder.cli import main

    path = tmp_path / "t.mcap"
    write_take(path, synthetic_samples(20)).close()
    runner = CliRunner()
    r = runner.invoke(main, ["log", "check", str(path)])
    assert r.exit_code == 0 and "complete" in r.output
    r = runner.invoke(main, ["log", "dump", str(path), "--jsonl", "--topic", "suits/imu"])
    assert r.exit_code == 0 and len(r.output.splitlines()) == 20
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    r = runner.invoke(main, ["log", "check", str(cut), "--json"])
    assert r.exit_code == 1 and json.loads(r.output)["complete"] is False
    r = runner.invoke(main, ["log", "repair", str(cut)])
    assert r.exit_code == 0 and "original kept" in r.output
    assert runner.invoke(main, ["log", "check", str(cut)]).exit_code == 0
    time.sleep(0)


def test_names_read_from_a_take_are_printed_escaped(tmp_path):
    """A take's topics come from the file: rich markup or terminal controls in one must neither crash
    `log check` / `log repair` nor reach the terminal raw."""
    from click.testing import CliRunner
    from mcap.writer import Writer

    from dualhuman_builder.cli import main

    path = tmp_path / "hostile.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start("x", "x")
        cid = w.register_channel("[/x]\x1b[2J[bold", "json", 0, {})
        w.add_message(cid, 1, b"{}", 1)
        w.finish()
    size = path.stat().st_size
    os.truncate(path, size - 40)  # the footer and part of the summary gone: a take cut off, which repair rebuilds
    runner = CliRunner()
    for args in (["log", "check", str(path)], ["log", "repair", str(path), "--out", str(tmp_path / "r.mcap")]):
        r = runner.invoke(main, args)
        assert r.exception is None or isinstance(r.exception, SystemExit), (args, r.output)
        assert "\x1b[2J" not in r.output, (args, r.output)
    assert "[/x]\\x1b[2J[bold: 1" in runner.invoke(main, ["log", "check", str(path)]).output

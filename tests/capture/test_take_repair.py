"""Takes that lost something: ``log repair`` recovers channels from the summary, re-decodes the samples
a crash left unwritten, fails cleanly on a full disk; ``replay --verify`` says when it did not verify;
chunk headers cannot make the reader allocate; mutated takes give only clear errors."""

from __future__ import annotations

import os
import shutil
import struct
import subprocess
import sys
import textwrap
import tracemalloc
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given
from hypothesis import strategies as st

from dualhuman_builder.body.mapping import MVN_SEGMENTS
from dualhuman_builder.capture.log.reader import MAGIC, TakeReader, check_take, dump_jsonl, read_columns, scan_take
from dualhuman_builder.capture.log.repair import repair_take
from dualhuman_builder.capture.log.writer import TakeWriter
from dualhuman_builder.capture.replay import verify_replay
from dualhuman_builder.capture.samples import SuitFrame
from dualhuman_builder.capture.sources import RawPacket, make_decoder
from dualhuman_builder.capture.wire.mvn import encode_frame
from dualhuman_builder.cli import main
from dualhuman_builder.errors import DualhumanError, FormatError

ROOT = Path(__file__).resolve().parents[2]
URL = "mvn+udp://127.0.0.1:9763"


def mvn_take(path: Path, frames: int = 120, written: int | None = None, crash: bool = False,
             chunk_size: int = 16 << 10) -> int:
    """A take of two suits (``frames`` poses each) as the recorder writes it: each pose's MVN
    datagrams raw, then the samples the real decoder gives. Only the first ``written`` samples are
    written (the decoding fell behind); ``crash``: the file is left without its index. Returns the
    number of samples the raw bytes decode to."""
    g = np.random.default_rng(0)
    w = TakeWriter(path, take="t", sources=[("suits", URL, "mvn")], bindings={"suits": {"mvn/0": {"actor": "alice"}}},
                   chunk_size=chunk_size)  # fmt: skip
    dec = make_decoder(URL)
    n = 0
    for k in range(frames):
        for c in (0, 1):
            q = g.normal(size=(23, 4))
            f = SuitFrame(c, k, 4 * k, 4_000_000 * k, 1_000_000_000 + 4_166_667 * k + c, tuple(MVN_SEGMENTS),
                          q / np.linalg.norm(q, axis=1, keepdims=True), g.normal(size=(23, 3)))  # fmt: skip
            for d in encode_frame(f, time_code=False):
                p = RawPacket(f.host_time_ns, d)
                w.add_raw(0, p)
                for s in dec.feed(p):
                    n += 1
                    if written is None or n <= written:
                        w.add_sample(0, s)
    w.close()
    if crash:  # killed after its last flush: everything up to the index, which is never written
        data = path.read_bytes()
        pos = len(MAGIC)
        while struct.unpack_from("<B", data, pos)[0] != 0x0F:
            pos += 9 + struct.unpack_from("<Q", data, pos + 1)[0]
        path.write_bytes(data[:pos])
    return n


def _text(result) -> str:
    """A command's output with the console's line wrapping undone."""
    return " ".join(result.output.split())


def chunk_offsets(path: Path) -> list[tuple[int, int]]:
    """``(offset, size)`` of every top-level chunk record."""
    data = path.read_bytes()
    out, pos = [], len(MAGIC)
    while pos + 9 <= len(data):
        op, length = struct.unpack_from("<BQ", data, pos)
        if op == 0x06:
            out.append((pos, 9 + length))
        if op == 0x02:
            break
        pos += 9 + length
    return out


def damage(path: Path, out: Path, chunks) -> None:
    """A copy of ``path`` with 64 bytes zeroed inside each chunk of ``chunks`` (offset, size)."""
    data = bytearray(path.read_bytes())
    for pos, size in chunks:
        data[pos + size // 2:pos + size // 2 + 64] = bytes(64)
    out.write_bytes(bytes(data))


# ---------------------------------------------------------------------- repair
def test_repair_recovers_the_channels_of_a_damaged_first_chunk_from_the_summary(tmp_path):
    """The first chunk holds every channel record. Damaged, it loses its own messages only: the
    summary section lists the channels, so the later chunks' messages are read, checked and kept,
    and what was lost is counted in bytes and in messages per topic."""
    path = tmp_path / "t.mcap"
    mvn_take(path, frames=200)
    intact = check_take(path)
    first = chunk_offsets(path)[0]
    bad = tmp_path / "bad.mcap"
    damage(path, bad, [first])
    rep = check_take(bad)
    assert not rep.ok and rep.lost_bytes == first[1]
    assert rep.lost_messages and sum(rep.lost_messages.values()) + rep.messages == intact.messages
    assert rep.per_topic + rep.lost_messages == intact.per_topic
    assert not any("channel record is lost" in p for p in rep.problems), rep.problems
    n = rep.per_topic["suits/mvn/1/SuitFrame"]
    assert len(read_columns(bad)["suits/mvn/1/SuitFrame"].columns["host_time_ns"]) == n
    fixed = repair_take(bad, tmp_path / "fixed.mcap")
    assert fixed.messages == rep.messages > intact.messages // 2
    assert fixed.lost_bytes == first[1] and fixed.lost_messages == rep.lost_messages
    assert any("summary" in line for line in fixed.recovered)
    again = check_take(tmp_path / "fixed.mcap")
    assert again.ok and again.per_topic == rep.per_topic
    r = CliRunner().invoke(main, ["log", "repair", str(bad), "--out", str(tmp_path / "cli.mcap")])
    assert r.exit_code == 0 and f"lost: {first[1]} bytes" in _text(r) and "lost: raw/suits:" in _text(r), r.output


@pytest.mark.parametrize("written", [0, 150])
def test_repair_redecodes_the_samples_a_crash_left_unwritten(tmp_path, written):
    """Killed while its decoding lagged (150 of 240 samples written), or on a disk that filled before
    any sample (0): the raw bytes are all there. ``replay --verify`` says samples are missing;
    ``log repair`` re-decodes them, writes them in time order beside the recorded ones, says so, and
    the repaired take verifies bit for bit."""
    path = tmp_path / "t.mcap"
    total = mvn_take(path, written=written, crash=True)
    before = verify_replay(path)
    assert before.missing == total - written and before.samples == written and not before.verified
    r = CliRunner().invoke(main, ["replay", str(path), "--verify"])
    assert r.exit_code == 1 and "`dualhuman log repair" in _text(r) and "object object" not in r.output, r.output
    rep = repair_take(path)
    assert rep.original == tmp_path / "t.damaged.mcap" and rep.original.exists()
    assert sum(rep.redecoded.values()) == total - written and any("re-decoded" in n for n in rep.notes)
    after = verify_replay(path)
    assert after.verified and after.samples == total, after
    for c in read_columns(path).values():
        assert np.all(np.diff(c.columns["host_time_ns"]) > 0)
    r = TakeReader(path)
    r.load_header()
    assert r.take_meta()["name"] == "t" and "repair" in {m for m in TakeReader(path).metadata} | set(_metadata(path))
    with pytest.raises(FormatError, match="nothing to repair"):
        repair_take(path)


def test_repair_keeps_an_earlier_damaged_copy(tmp_path):
    path = tmp_path / "t.mcap"
    mvn_take(path, frames=20, crash=True)
    earlier = tmp_path / "t.damaged.mcap"
    earlier.write_bytes(b"the original of an earlier repair")
    rep = repair_take(path)
    assert rep.original == tmp_path / "t.damaged-2.mcap" and rep.original.exists()
    assert earlier.read_bytes() == b"the original of an earlier repair"


_REPAIR_SCRIPT = textwrap.dedent("""
    import resource, signal, sys
    if {limit}:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, ({limit}, {limit}))
    from dualhuman_builder.cli import main
    sys.argv = ["dualhuman", "log", "repair", {path!r}]
    main()
""")


def _can_mount_tmpfs() -> bool:
    if shutil.which("unshare") is None:
        return False
    return subprocess.run(["unshare", "-rm", "sh", "-c", "mount -t tmpfs -o size=64k none /tmp"],
                          capture_output=True).returncode == 0  # fmt: skip


@pytest.mark.parametrize("how", [
    "file-size limit",
    # a real full disk needs a tmpfs mounted in an unprivileged user namespace; some kernels and
    # containers forbid those, and there the file-size limit above is the check that runs
    pytest.param("full tmpfs", marks=pytest.mark.skipif(not _can_mount_tmpfs(),
                                                        reason="no unprivileged user namespace to mount a tmpfs in")),
])  # fmt: skip
def test_repair_on_a_full_disk_is_a_clear_error_that_leaves_nothing_behind(tmp_path, how):
    """Writing the repaired take runs out of room (a real ``ENOSPC`` on a small tmpfs mounted in a
    user namespace, or ``EFBIG`` past ``RLIMIT_FSIZE``): exit 2 with the reason and the fix, no
    traceback, no partial file, the take untouched; with room again, the repair succeeds."""
    src = tmp_path / "src.mcap"
    mvn_take(src, frames=300, crash=True)
    size = src.stat().st_size
    folder = tmp_path / "disk"
    folder.mkdir()
    path = folder / "t.mcap"
    shutil.copy(src, path)
    if how == "file-size limit":
        cmd = [sys.executable, "-c", _REPAIR_SCRIPT.format(limit=size // 2, path=str(path))]
        reason = "the file-size limit was reached"
    else:
        script = _REPAIR_SCRIPT.format(limit=0, path=str(path))
        cmd = ["unshare", "-rm", "sh", "-c", f'mount -t tmpfs -o size={(size * 3 // 2) // 1024}k none "$0" && '
               f'cp "$1" "$0/t.mcap" && "$2" -c "$3"; rc=$?; ls -A "$0"; exit $rc',
               str(folder), str(src), sys.executable, script]  # fmt: skip
        reason = "the disk is full"
    out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert out.returncode == 2, out.stdout + out.stderr
    assert f"repairing the take stopped: {reason}" in out.stderr and "fix: free space" in out.stderr, out.stderr
    assert "Traceback" not in out.stderr and "OSError" not in out.stderr
    if how == "full tmpfs":
        assert out.stdout.split() == ["t.mcap"]  # what was left on the full disk
    else:
        assert sorted(p.name for p in folder.iterdir()) == ["t.mcap"]
        assert path.read_bytes() == src.read_bytes()
        assert repair_take(path).messages > 0 and check_take(path).ok


# ---------------------------------------------------------------------- replay --verify
def test_replay_verify_fails_clearly_where_it_did_not_verify(tmp_path):
    """Every chunk damaged: not verified, exit 1 (nothing was compared). Cut off: the samples the
    raw bytes hold beyond the recorded ones are named, with the fix. An MCAP file that no capture
    wrote (no take metadata): a clear error, exit 2."""
    from mcap.writer import Writer

    runner = CliRunner()
    path = tmp_path / "t.mcap"
    mvn_take(path, frames=60)
    assert runner.invoke(main, ["replay", str(path), "--verify"]).exit_code == 0
    bad = tmp_path / "bad.mcap"
    damage(path, bad, chunk_offsets(path))
    r = runner.invoke(main, ["replay", str(bad), "--verify"])
    assert r.exit_code == 1 and "not verified: the take is damaged" in _text(r), r.output
    assert "damaged chunk" in _text(r)
    assert not verify_replay(bad).verified
    cut = tmp_path / "cut.mcap"
    data = path.read_bytes()
    cut.write_bytes(data[: chunk_offsets(path)[-1][0] + 40])
    r = runner.invoke(main, ["replay", str(cut), "--verify"])
    assert r.exit_code == 1 and "object object" not in r.output and "did not finish" in _text(r), r.output
    plain = tmp_path / "plain.mcap"
    with open(plain, "wb") as f:
        w = Writer(f)
        w.start("", "test")
        cid = w.register_channel("raw/x", "dualhuman.raw", 0, {})
        w.add_message(cid, 1, b"\x00" * 8, 1)
        w.finish()
    r = runner.invoke(main, ["replay", str(plain), "--verify"])
    assert r.exit_code == 2 and "no take metadata" in _text(r) and "KeyError" not in r.output, r.output


# ---------------------------------------------------------------------- headers that lie
def _lz4_zeros(n: int) -> bytes:
    import lz4.frame

    c = lz4.frame.LZ4FrameCompressor()
    parts = [c.begin()]
    block = bytes(min(n, 1 << 20))
    for _ in range(n // len(block)):
        parts.append(c.compress(block))
    parts.append(c.flush())
    return b"".join(parts)


def _zstd_zeros(n: int) -> bytes:
    import zstandard

    return zstandard.ZstdCompressor().compress(bytes(n))


def _mcap_with_chunk(chunk, *, complete: bool, index_at: int | None = None) -> bytes:
    """An MCAP file: header, a channel, ``chunk``, a top-level message; with ``complete``, a summary
    whose chunk index points at the chunk (or at byte ``index_at`` of the message's data)."""
    from mcap.data_stream import RecordBuilder
    from mcap.records import Channel, ChunkIndex, DataEnd, Footer, Header, Message

    b = RecordBuilder()
    Header(profile="dualhuman", library="test").write(b)
    ch = Channel(id=1, topic="raw/x", message_encoding="dualhuman.raw", schema_id=0, metadata={})
    ch.write(b)
    at = len(MAGIC) + b.count
    chunk.write(b)
    length = len(MAGIC) + b.count - at
    data_at = len(MAGIC) + b.count + 9 + 22
    huge = b"\x06" + (1 << 60).to_bytes(8, "little")  # a record header claiming 2**60 bytes
    Message(channel_id=1, sequence=0, log_time=1, publish_time=1, data=huge).write(b)
    if complete:
        DataEnd(0).write(b)
        start = len(MAGIC) + b.count
        ch.write(b)
        ChunkIndex(chunk_length=length, chunk_start_offset=at if index_at is None else data_at,
                   compression=chunk.compression, compressed_size=len(chunk.data), message_end_time=1,
                   message_index_length=0, message_index_offsets={}, message_start_time=1,
                   uncompressed_size=chunk.uncompressed_size).write(b)  # fmt: skip
        Footer(summary_start=start, summary_offset_start=0, summary_crc=0).write(b)
    return MAGIC + b.end() + (MAGIC if complete else b"")


@pytest.mark.parametrize("case", ["claims 1 TiB", "lz4 bomb", "lz4 beyond its claim", "zstd beyond its claim",
                                  "index at a huge record"])  # fmt: skip
def test_chunk_headers_are_checked_before_anything_is_allocated(tmp_path, case):
    """A chunk's uncompressed size, its decompressed output and a record length the chunk index
    points at are checked against the bytes present: a bomb is reported as a damaged chunk, reading
    it takes a few MiB, never what the headers claim."""
    from mcap.records import Chunk

    small = _lz4_zeros(64 << 10)
    chunk = {"claims 1 TiB": Chunk(compression="lz4", data=small, message_start_time=1, message_end_time=1,
                                   uncompressed_crc=0, uncompressed_size=1 << 40),
             "lz4 bomb": Chunk(compression="lz4", data=_lz4_zeros(80 << 20), message_start_time=1, message_end_time=1,
                               uncompressed_crc=0, uncompressed_size=80 << 20),
             "lz4 beyond its claim": Chunk(compression="lz4", data=_lz4_zeros(40 << 20), message_start_time=1,
                                           message_end_time=1, uncompressed_crc=0, uncompressed_size=4000),
             "zstd beyond its claim": Chunk(compression="zstd", data=_zstd_zeros(40 << 20), message_start_time=1,
                                            message_end_time=1, uncompressed_crc=0, uncompressed_size=4000),
             "index at a huge record": Chunk(compression="lz4", data=small, message_start_time=1, message_end_time=1,
                                             uncompressed_crc=0, uncompressed_size=64 << 10)}[case]  # fmt: skip
    for complete in (False, True):
        path = tmp_path / f"{case.replace(' ', '-')}-{complete}.mcap"
        path.write_bytes(_mcap_with_chunk(chunk, complete=complete, index_at=0 if case.startswith("index") else None))
        tracemalloc.start()
        try:
            rep = check_take(path)
            problems: list[str] = []
            read_columns(path, problems)
            TakeReader(path).message_data(lambda ch: True)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 12 << 20, f"{peak / 2**20:.0f} MiB"
        if case != "index at a huge record":
            assert any("damaged chunk" in p for p in rep.problems), rep.problems
            assert rep.messages == 1 and rep.lost_bytes == chunk_offsets(path)[0][1]


# ---------------------------------------------------------------------- mutated takes
@pytest.fixture(scope="module")
def small_takes(tmp_path_factory) -> list[bytes]:
    """A small real take (LZ4 chunks with CRCs), and the same rewritten with uncompressed chunks and
    no CRCs, so that mutations reach the record parsers and the sample decoder."""
    from mcap.writer import CompressionType, Writer

    d = tmp_path_factory.mktemp("small")
    path = d / "t.mcap"
    mvn_take(path, frames=6, chunk_size=2 << 10)
    r = TakeReader(path)
    plain = d / "plain.mcap"
    with open(plain, "wb") as f:
        w = Writer(f, compression=CompressionType.NONE, chunk_size=2 << 10, enable_crcs=False)
        w.start("dualhuman", "test")
        sids: dict[int, int] = {}
        cids: dict[int, int] = {}
        for ch, msg in r.messages():
            if ch.id not in cids:
                if ch.schema_id:
                    sc = r.schemas[ch.schema_id]
                    sids.setdefault(sc.id, w.register_schema(sc.name, sc.encoding, sc.data))
                sid = sids.get(ch.schema_id, 0)
                cids[ch.id] = w.register_channel(ch.topic, ch.message_encoding, sid, dict(ch.metadata))
            w.add_message(cids[ch.id], msg.log_time, bytes(msg.data), msg.publish_time)
        for name, meta in r.metadata.items():
            w.add_metadata(name, meta)
        w.finish()
    return [path.read_bytes(), plain.read_bytes()]


@st.composite
def mutations(draw, n: int):
    edits = []
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["flip", "set", "insert", "delete", "truncate"]))
        pos = draw(st.integers(0, n - 1))
        edits.append((kind, pos, draw(st.binary(min_size=1, max_size=9))))
    return edits


def _mutate(data: bytes, edits) -> bytes:
    b = bytearray(data)
    for kind, pos, blob in edits:
        pos = min(pos, max(len(b) - 1, 0))
        if kind == "flip":
            b[pos] ^= blob[0] or 1
        elif kind == "set":
            b[pos:pos + len(blob)] = blob
        elif kind == "insert":
            b[pos:pos] = blob
        elif kind == "delete":
            del b[pos:pos + len(blob)]
        else:
            del b[pos:]
    return bytes(b)


@given(which=st.integers(0, 1), edits=mutations(40_000))
def test_mutated_takes_give_only_clear_errors_and_bounded_memory(small_takes, tmp_path, which, edits):
    """Bytes of a small real take flipped, overwritten, inserted, deleted or cut: reading, checking,
    dumping, verifying and repairing it raise nothing but a DualhumanError, and stay within a few
    MiB."""
    path = tmp_path / f"m{os.getpid()}.mcap"
    out = tmp_path / f"m{os.getpid()}.fixed.mcap"
    for p in (path, out):
        p.unlink(missing_ok=True)
    path.write_bytes(_mutate(small_takes[which], [(k, p % len(small_takes[which]), b) for k, p, b in edits]))
    tracemalloc.start()
    try:
        for op in (lambda: list(TakeReader(path).records()), lambda: list(TakeReader(path).samples()),
                   lambda: read_columns(path), lambda: check_take(path), lambda: dump_jsonl(path, _Null(), raw=True),
                   lambda: verify_replay(path), lambda: repair_take(path, out)):  # fmt: skip
            try:
                op()
            except DualhumanError:
                pass
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 24 << 20, f"{peak / 2**20:.0f} MiB"
    if out.exists():
        assert check_take(out).complete


def _metadata(path: Path) -> list[str]:
    r = TakeReader(path)
    for _ in r.records():
        pass
    return sorted(r.metadata)


class _Null:
    def write(self, _text: str) -> int:
        return 0


def test_scan_and_reader_counts_are_per_pass(tmp_path):
    """Reading a damaged take twice with one reader reports its damage once, not twice."""
    path = tmp_path / "t.mcap"
    mvn_take(path, frames=60)
    bad = tmp_path / "bad.mcap"
    damage(path, bad, chunk_offsets(path)[:1])
    r = TakeReader(bad)
    for _ in range(2):
        n = Counter(ch.topic for ch, _ in r.messages())
        assert len(r.problems) == 1 and r.lost_bytes == chunk_offsets(path)[0][1], r.problems
    assert n["raw/suits"] > 0 and scan_take(bad).complete

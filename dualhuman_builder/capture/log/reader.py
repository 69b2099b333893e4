"""Read takes back, tolerant of damage: check, repair, dump, and the packets and samples for replay.

A take cut off by a crash, ``kill -9`` or a full disk has no index (summary and footer) and may end in
a partial record. :class:`TakeReader` scans the top-level records first (opcode + length, no
payload read), keeps the prefix of complete records, and reads that in file order with the
``mcap`` library's record parsers; a chunk whose CRC or compression is broken is skipped and
reported, never silently used. :func:`check_take` says what a file holds and what is lost;
:func:`repair_take` rewrites it with a full index (the original is kept beside it).
"""

from __future__ import annotations

import io
import json
import os
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from mcap.records import Attachment, Channel, Chunk, Message, Metadata, Schema
from mcap.stream_reader import StreamReader

from dualhuman_builder.capture.log import schemas
from dualhuman_builder.capture.log.mcapio import OP_CHANNEL, OP_MESSAGE, OP_SCHEMA, iter_chunk_records, message_fields
from dualhuman_builder.capture.sources import RawPacket
from dualhuman_builder.errors import FormatError

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")
_OP_FOOTER = 0x02
_OP_CHUNK = 0x06


@dataclass
class TakeScan:
    """Top-level structure of a file: ``size`` bytes; ``good_end`` the end offset of the last
    complete record; ``complete`` True when the footer and closing magic are present; ``tail``
    a description of the bytes after ``good_end`` (None if there are none)."""

    size: int
    good_end: int
    complete: bool
    records: int
    chunks: int
    tail: str | None


@dataclass(frozen=True, slots=True)
class _Msg:
    channel_id: int
    sequence: int
    log_time: int
    publish_time: int
    data: memoryview


def _decompress(chunk) -> bytes:
    if chunk.compression == "":
        data = chunk.data
    elif chunk.compression == "lz4":
        import lz4.frame

        data = lz4.frame.decompress(chunk.data)
    elif chunk.compression == "zstd":
        import zstandard

        data = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
    else:
        raise ValueError(f"unknown chunk compression {chunk.compression!r}")
    if len(data) != chunk.uncompressed_size:
        raise ValueError(f"chunk decompresses to {len(data)} bytes, its header says {chunk.uncompressed_size}")
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch")
    return data


def _chunk_items(chunk) -> Iterator[tuple]:
    from mcap.data_stream import ReadDataStream

    for op, body in iter_chunk_records(_decompress(chunk)):
        if op == OP_MESSAGE:
            yield ("msg", *message_fields(body))
        elif op == OP_SCHEMA:
            yield ("rec", Schema.read(ReadDataStream(io.BytesIO(bytes(body)))))
        elif op == OP_CHANNEL:
            yield ("rec", Channel.read(ReadDataStream(io.BytesIO(bytes(body)))))


def scan_take(path: str | Path) -> TakeScan:
    """Walk the top-level records of ``path`` by their lengths (lengths are checked against the
    file size, never trusted). Raises FormatError if the file is not MCAP at all."""
    path = Path(path)
    size = path.stat().st_size
    with open(path, "rb") as f:
        if f.read(len(MAGIC)) != MAGIC:
            raise FormatError("not an MCAP file (bad magic)", path=path, fix="give the take's .mcap file")
        pos, records, chunks = len(MAGIC), 0, 0
        while True:
            head = f.read(_RECORD_HEAD.size)
            if len(head) < _RECORD_HEAD.size:
                tail = None if not head else f"{len(head)} bytes of a record header"
                return TakeScan(size, pos, False, records, chunks, tail)
            opcode, length = _RECORD_HEAD.unpack(head)
            end = pos + _RECORD_HEAD.size + length
            if end > size:
                tail = f"a record (opcode 0x{opcode:02x}) of {length} bytes cut off after {size - pos - 9}"
                return TakeScan(size, pos, False, records, chunks, tail)
            f.seek(end)
            pos = end
            records += 1
            chunks += opcode == _OP_CHUNK
            if opcode == _OP_FOOTER:
                closing = f.read(len(MAGIC))
                complete = closing == MAGIC and pos + len(MAGIC) == size
                return TakeScan(size, pos + len(closing), complete, records, chunks,
                                None if complete else "bad closing magic")  # fmt: skip


class _Prefix(io.RawIOBase):
    """The first ``end`` bytes of a file, as a stream (so the reader never sees a partial record)."""

    def __init__(self, f, end: int):
        self._f, self._left = f, end

    def readable(self) -> bool:
        return True

    def readinto(self, b) -> int:
        n = min(len(b), self._left)
        if n <= 0:
            return 0
        data = self._f.read(n)
        b[: len(data)] = data
        self._left -= len(data)
        return len(data)


class TakeReader:
    """Records of a take in file order, up to its last complete record.

    ``problems``: what was skipped (bad chunks) or cut off; ``schemas`` / ``channels`` by id and
    ``metadata`` by name fill in while :meth:`records` runs (:meth:`load_header` reads them all
    first)."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.scan = scan_take(self.path)
        self.problems: list[str] = []
        if self.scan.tail:
            self.problems.append(f"file ends in {self.scan.tail} (lost: {self.scan.size - self.scan.good_end} bytes)")
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: list[Attachment] = []

    def _items(self) -> Iterator[tuple]:
        """``("msg", channel id, sequence, log time, publish time, data)`` for messages (data a
        memoryview) and ``("rec", record)`` for every other record, in file order."""
        from mcap.exceptions import EndOfFile, McapError

        with open(self.path, "rb") as f:
            reader = StreamReader(io.BufferedReader(_Prefix(f, self.scan.good_end)), emit_chunks=True,
                                  validate_crcs=False, record_size_limit=self.scan.size)  # fmt: skip
            it = reader.records
            while True:
                try:
                    rec = next(it)
                except (StopIteration, EndOfFile):
                    return
                except (McapError, struct.error, ValueError) as e:
                    self.problems.append(f"unreadable record after {len(self.channels)} channels: {e}")
                    return
                if isinstance(rec, Chunk):
                    try:
                        items = list(_chunk_items(rec))
                    except Exception as e:  # noqa: BLE001 - any decode failure of one chunk: skip it, say so
                        self.problems.append(f"skipped a damaged chunk ({rec.message_start_time}..."
                                             f"{rec.message_end_time} ns): {type(e).__name__}: {e}")
                        continue
                    for item in items:
                        if item[0] == "rec":
                            self._note(item[1])
                        yield item
                elif isinstance(rec, Message):
                    yield ("msg", rec.channel_id, rec.sequence, rec.log_time, rec.publish_time, memoryview(rec.data))
                else:
                    self._note(rec)
                    yield ("rec", rec)

    def records(self) -> Iterator:
        """Every record (chunks opened, messages as ``mcap`` Message records) in file order."""
        for item in self._items():
            if item[0] == "msg":
                _, ch, seq, lt, pt, data = item
                yield Message(channel_id=ch, sequence=seq, log_time=lt, publish_time=pt, data=bytes(data))
            else:
                yield item[1]

    def _note(self, rec) -> None:
        if isinstance(rec, Schema):
            self.schemas[rec.id] = rec
        elif isinstance(rec, Channel):
            self.channels[rec.id] = rec
        elif isinstance(rec, Metadata):
            self.metadata[rec.name] = dict(rec.metadata)
        elif isinstance(rec, Attachment):
            self.attachments.append(rec)

    def messages(self) -> Iterator[tuple[Channel, Message]]:
        """``(channel, message)`` in file order (message data as a memoryview)."""
        channels = self.channels
        for item in self._items():
            if item[0] != "msg":
                continue
            ch = channels.get(item[1])
            if ch is None:
                self.problems.append(f"message on unknown channel {item[1]}")
                continue
            yield ch, _Msg(item[1], item[2], item[3], item[4], item[5])

    # ------------------------------------------------------------------ take contents
    def take_meta(self) -> dict[str, Any]:
        """The ``take`` metadata (sources and bindings parsed from JSON)."""
        meta = dict(self.metadata.get("take", {}))
        for k in ("sources", "bindings"):
            if k in meta:
                meta[k] = json.loads(meta[k])
        return meta

    def load_header(self) -> None:
        """Read the metadata records near the start (take, software, rig) without the rest."""
        for rec in self.records():
            if isinstance(rec, Message):
                return

    def raw_packets(self) -> Iterator[tuple[str, RawPacket]]:
        """``(source name, packet)`` for every raw message, in recorded order."""
        for ch, msg in self.messages():
            if ch.topic.startswith("raw/"):
                yield ch.metadata.get("source", ch.topic[4:]), RawPacket(msg.log_time, bytes(msg.data))

    def samples(self) -> Iterator[tuple[str, Any]]:
        """``(source name, sample)`` for every decoded sample, in recorded order."""
        classes = schemas.sample_classes()
        layouts: dict[int, schemas.Layout] = {}
        for ch, msg in self.messages():
            if ch.message_encoding != schemas.MESSAGE_ENCODING:
                continue
            layout = layouts.get(ch.id)
            if layout is None:
                sc = self.schemas[ch.schema_id]
                layout = layouts[ch.id] = schemas.parse_definition(sc.name, sc.data.decode(), classes)
            yield ch.metadata.get("source", ""), schemas.decode(layout, msg.data)


@dataclass
class ChannelColumns:
    """All decoded samples of one channel as arrays: ``columns[field]`` has the samples along
    axis 0 (``(N,)`` for scalars, ``(N, *shape)`` for arrays; strings: the one shared value)."""

    topic: str
    source: str
    entity: str
    sample_type: str
    metadata: dict[str, str]
    count: int
    columns: dict[str, Any]


def read_columns(path: str | Path) -> dict[str, ChannelColumns]:
    """Every decoded-sample channel of a take as arrays, by topic — the fast way to hand a take to
    the pipeline (a channel whose messages differ in layout is decoded message by message and
    stacked)."""
    import numpy as np

    r = TakeReader(path)
    datas: dict[int, list] = {}
    for item in r._items():
        if item[0] == "msg":
            datas.setdefault(item[1], []).append(item[5])
    classes = schemas.sample_classes()
    out = {}
    for cid, ds in datas.items():
        ch = r.channels.get(cid)
        if ch is None or ch.message_encoding != schemas.MESSAGE_ENCODING:
            continue
        sc = r.schemas[ch.schema_id]
        layout = schemas.parse_definition(sc.name, sc.data.decode(), classes)
        cols = schemas.decode_columns(layout, ds)
        if cols is None:
            samples = [schemas.decode(layout, d) for d in ds]
            cols = {}
            for f in layout.fields:
                vals = [getattr(s, f.name) for s in samples]
                same = f.kind in ("str", "strs") and all(v == vals[0] for v in vals)
                cols[f.name] = vals[0] if same else (np.stack(vals) if f.kind == "array" and
                                                     len({np.shape(v) for v in vals}) == 1 else
                                                     np.asarray(vals) if f.kind != "array" else vals)  # fmt: skip
        md = dict(ch.metadata)
        out[ch.topic] = ChannelColumns(ch.topic, md.get("source", ""), md.get("entity", ""), layout.cls.__name__, md,
                                       len(ds), cols)  # fmt: skip
    return out


# ---------------------------------------------------------------------- check and repair
@dataclass
class CheckReport:
    path: Path
    size: int
    complete: bool
    readable_bytes: int
    lost_bytes: int
    chunks: int
    messages: int
    per_topic: Counter = field(default_factory=Counter)
    metadata: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    first_ns: int | None = None
    last_ns: int | None = None

    @property
    def ok(self) -> bool:
        """Complete and nothing skipped."""
        return self.complete and not self.problems

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "ok": self.ok, "complete": self.complete, "size": self.size,
                "readable_bytes": self.readable_bytes, "lost_bytes": self.lost_bytes, "chunks": self.chunks,
                "messages": self.messages, "per_topic": dict(self.per_topic), "metadata": self.metadata,
                "problems": self.problems, "first_ns": self.first_ns, "last_ns": self.last_ns,
                "duration_s": None if self.first_ns is None else (self.last_ns - self.first_ns) / 1e9}  # fmt: skip


def check_take(path: str | Path) -> CheckReport:
    """Read the whole take (CRCs checked) and say what it holds and what, if anything, is lost."""
    r = TakeReader(path)
    per_topic: Counter = Counter()
    first = last = None
    n = 0
    for ch, msg in r.messages():
        per_topic[ch.topic] += 1
        n += 1
        t = msg.log_time
        first = t if first is None or t < first else first
        last = t if last is None or t > last else last
    if not r.scan.complete and not r.scan.tail:
        r.problems.append("no index (summary and footer): the recording did not finish — run `dualhuman log repair`")
    return CheckReport(r.path, r.scan.size, r.scan.complete, r.scan.good_end, r.scan.size - r.scan.good_end,
                       r.scan.chunks, n, per_topic, sorted(r.metadata), list(r.problems), first, last)  # fmt: skip


@dataclass
class RepairReport:
    path: Path
    original: Path | None
    messages: int
    lost_bytes: int
    problems: list[str]


def repair_take(path: str | Path, out: str | Path | None = None) -> RepairReport:
    """Rewrite ``path`` with everything readable and a full index. With ``out``, write there and
    leave ``path`` alone; else the repaired file takes ``path``'s place and the original is kept as
    ``<stem>.damaged.mcap``. Raises FormatError if the file is already complete and intact."""
    from mcap.writer import CompressionType, Writer

    from dualhuman_builder.capture.log.writer import PROFILE

    path = Path(path)
    pre = scan_take(path)
    r = TakeReader(path)
    target = Path(out) if out is not None else path.with_name(path.stem + ".repairing.mcap")
    if target.exists():
        raise FormatError("the repair target exists already", path=target, fix="remove it or give another --out")
    schema_ids: dict[int, int] = {}
    channel_ids: dict[int, int] = {}
    n = 0
    with open(target, "xb") as f:
        w = Writer(f, compression=CompressionType.LZ4)
        w.start(PROFILE, "dualhuman_builder")
        for rec in r.records():
            if isinstance(rec, Schema):
                schema_ids[rec.id] = w.register_schema(rec.name, rec.encoding, rec.data)
            elif isinstance(rec, Channel):
                if rec.id not in channel_ids:
                    channel_ids[rec.id] = w.register_channel(rec.topic, rec.message_encoding,
                                                             schema_ids.get(rec.schema_id, 0), dict(rec.metadata))  # fmt: skip
            elif isinstance(rec, Message):
                cid = channel_ids.get(rec.channel_id)
                if cid is not None:
                    w.add_message(cid, rec.log_time, rec.data, rec.publish_time, rec.sequence)
                    n += 1
            elif isinstance(rec, Metadata):
                w.add_metadata(rec.name, dict(rec.metadata))
            elif isinstance(rec, Attachment):
                w.add_attachment(rec.create_time, rec.log_time, rec.name, rec.media_type, rec.data)
        if pre.complete and not r.problems:
            f.close()
            target.unlink()
            raise FormatError("the take is complete and intact; nothing to repair", path=path)
        w.add_metadata("repair", {"original_size": str(pre.size), "lost_bytes": str(pre.size - pre.good_end),
                                  "problems": json.dumps(r.problems)})  # fmt: skip
        w.finish()
        f.flush()
        os.fsync(f.fileno())
    original = None
    if out is None:
        original = path.with_name(path.stem + ".damaged.mcap")
        os.replace(path, original)
        os.replace(target, path)
        target = path
    return RepairReport(target, original, n, pre.size - pre.good_end, list(r.problems))


# ---------------------------------------------------------------------- dump
def _jsonable(v):
    import numpy as np

    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, tuple):
        return list(v)
    return v


def dump_jsonl(path: str | Path, out, *, raw: bool = False, topics: tuple[str, ...] = ()) -> int:
    """Write every decoded sample of a take as one JSON object per line to ``out`` (a text
    stream): ``topic``, ``source``, ``entity``, ``actor`` (when bound), ``type``, then the sample's
    fields (SI units: metres, m/s, rad/s, m/s^2; quaternions x, y, z, w; times int ns). ``raw``
    also writes the raw packets (``data_hex``). ``topics``: only topics starting with one of these.
    Returns the number of lines."""
    r = TakeReader(path)
    classes = schemas.sample_classes()
    layouts: dict[int, schemas.Layout] = {}
    n = 0
    for ch, msg in r.messages():
        if topics and not ch.topic.startswith(topics):
            continue
        md = ch.metadata
        if ch.message_encoding == schemas.MESSAGE_ENCODING:
            layout = layouts.get(ch.id)
            if layout is None:
                sc = r.schemas[ch.schema_id]
                layout = layouts[ch.id] = schemas.parse_definition(sc.name, sc.data.decode(), classes)
            sample = schemas.decode(layout, msg.data)
            row = {"topic": ch.topic, "source": md.get("source"), "entity": md.get("entity"), "actor": md.get("actor"),
                   "type": layout.cls.__name__}  # fmt: skip
            row.update({f.name: _jsonable(getattr(sample, f.name)) for f in layout.fields})
        elif raw and ch.topic.startswith("raw/"):
            row = {"topic": ch.topic, "source": md.get("source"), "type": "raw", "host_time_ns": msg.log_time,
                   "data_hex": msg.data.hex()}  # fmt: skip
        else:
            continue
        out.write(json.dumps(row, allow_nan=True) + "\n")
        n += 1
    return n

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
from typing import Any, Callable, Iterator

from mcap.records import Attachment, Channel, Chunk, Header, Message, Metadata, Schema

from dualhuman_builder.capture.log import schemas
from dualhuman_builder.capture.log.mcapio import OP_CHANNEL, OP_MESSAGE, OP_SCHEMA, iter_chunk_records, message_fields
from dualhuman_builder.capture.sources import RawPacket
from dualhuman_builder.errors import FormatError

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")
_OP_FOOTER = 0x02
_OP_CHUNK = 0x06
_OP_DATA_END = 0x0F


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


#: Top-level records whose content we read (others, the indexes, are skipped).
_CONTENT = {0x01: Header, OP_SCHEMA: Schema, OP_CHANNEL: Channel, OP_MESSAGE: Message, _OP_CHUNK: Chunk,
            0x09: Attachment, 0x0C: Metadata}  # fmt: skip


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


def _parse(op: int, body: bytes):
    """A top-level record from its body, with the ``mcap`` library's record parsers."""
    from mcap.data_stream import ReadDataStream

    stream = ReadDataStream(io.BytesIO(body))
    if op == OP_MESSAGE:
        return Message.read(stream, len(body))
    return _CONTENT[op].read(stream)


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

    def _top(self) -> Iterator[tuple[int, bytes]]:
        """``(opcode, body)`` of the top-level records of the data section that carry content
        (header, schemas, channels, messages, chunks, metadata, attachments), in file order; index
        records are skipped by seeking (their content is rebuilt from the data when needed)."""
        end = self.scan.good_end
        head = _RECORD_HEAD
        with open(self.path, "rb") as f:
            f.seek(len(MAGIC))
            pos = len(MAGIC)
            while pos + head.size <= end:
                op, length = head.unpack(f.read(head.size))
                if op == _OP_DATA_END or op == _OP_FOOTER:
                    return
                if op in _CONTENT:
                    body = f.read(length)
                    if len(body) < length:
                        return
                    yield op, body
                else:
                    f.seek(length, 1)
                pos += head.size + length

    def _items(self) -> Iterator[tuple]:
        """``("msg", channel id, sequence, log time, publish time, data)`` for messages (data a
        memoryview) and ``("rec", record)`` for every other record, in file order."""
        for op, body in self._top():
            if op == OP_MESSAGE:
                yield ("msg", *message_fields(memoryview(body)))
                continue
            try:
                rec = _parse(op, body)
            except Exception as e:  # noqa: BLE001 - a damaged record: say so, go on with the next
                self.problems.append(f"unreadable record (opcode 0x{op:02x}): {type(e).__name__}: {e}")
                continue
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
            else:
                self._note(rec)
                yield ("rec", rec)

    def message_data(self, wanted: Callable[[Channel], bool]) -> dict[int, list]:
        """The data of every message on the channels ``wanted`` accepts, per channel id, in file
        order — the fast path (no per-message objects). Each list holds memoryviews of single
        messages and/or 2-D uint8 arrays of equal-length messages, one row per message.

        A complete take is read through its index (the summary's channels and chunk indexes, each
        chunk's message index: gathered with numpy, no per-message Python); a take without an index
        (cut off) by scanning every record."""
        if self.scan.complete and not self.problems:
            try:
                return self._indexed_message_data(wanted)
            except Exception as e:  # noqa: BLE001 - an index we cannot use: scan the records instead
                self.problems.append(f"index unusable ({type(e).__name__}: {e}); records scanned instead")
        return self._scanned_message_data(wanted)

    def _indexed_message_data(self, wanted: Callable[[Channel], bool]) -> dict[int, list]:
        import numpy as np
        from mcap.reader import make_reader

        def windows(buf, width: int):
            """Every ``width``-byte window of ``buf`` as rows of a read-only view (no copy)."""
            return np.ndarray((len(buf) - width + 1, width), dtype=np.uint8, buffer=buf, strides=(1, 1))

        with open(self.path, "rb") as f:
            summary = make_reader(f).get_summary()
            if summary is None or not summary.chunk_indexes:
                raise ValueError("no chunk index")
            self.schemas.update(summary.schemas)
            self.channels.update(summary.channels)
            keep = {cid for cid, ch in summary.channels.items() if wanted(ch)}
            out: dict[int, list] = {cid: [] for cid in keep}
            size = self.scan.size
            for ci in sorted(summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
                if ci.chunk_start_offset + ci.chunk_length > size:
                    raise ValueError("chunk index points past the end of the file")
                f.seek(ci.chunk_start_offset)
                head = f.read(9)
                op, length = _RECORD_HEAD.unpack(head)
                if op != _OP_CHUNK:
                    raise ValueError(f"chunk index points at a record of opcode 0x{op:02x}")
                data = _decompress(_parse(op, f.read(length)))
                u8 = data
                wanted_here = [(cid, off) for cid, off in ci.message_index_offsets.items() if cid in keep]
                for cid, off in wanted_here:
                    f.seek(off)
                    op, length = _RECORD_HEAD.unpack(f.read(9))
                    body = f.read(length)
                    if op != 0x07 or len(body) < 6:
                        raise ValueError("bad message index record")
                    n_bytes = struct.unpack_from("<I", body, 2)[0]
                    if 6 + n_bytes > len(body) or n_bytes % 16:
                        raise ValueError("message index longer than its record")
                    offsets = np.sort(np.frombuffer(body, dtype="<u8", count=n_bytes // 8, offset=6)[1::2]).astype(np.int64)
                    if len(offsets) == 0:
                        continue
                    if offsets[-1] + 31 > len(data):
                        raise ValueError("message index offset past the chunk")
                    lens = windows(u8, 8)[offsets + 1].copy().view("<u8").ravel().astype(np.int64) - 22
                    if lens.min() < 0 or (offsets + 31 + lens).max() > len(data):
                        raise ValueError("message record length past the chunk")
                    if (lens == lens[0]).all():
                        out[cid].append(windows(u8, int(lens[0]))[offsets + 31])  # rows gathered, index per row only
                    else:
                        mv = memoryview(data)
                        out[cid].extend(mv[o + 31:o + 31 + n] for o, n in zip(offsets.tolist(), lens.tolist()))
        return out

    def _scanned_message_data(self, wanted: Callable[[Channel], bool]) -> dict[int, list]:
        out: dict[int, list] = {}
        for item in self._items():
            if item[0] == "msg":
                data = out.get(item[1])
                if data is not None:
                    data.append(item[5])
            elif isinstance(item[1], Channel) and wanted(item[1]):
                out.setdefault(item[1].id, [])
        return out

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


def _count(parts: list) -> int:
    return sum(len(p) if getattr(p, "ndim", 1) == 2 else 1 for p in parts)


def _split_rows(parts: list) -> list:
    out = []
    for p in parts:
        if getattr(p, "ndim", 1) == 2:
            out.extend(p[i].tobytes() for i in range(len(p)))
        else:
            out.append(p)
    return out


def read_columns(path: str | Path) -> dict[str, ChannelColumns]:
    """Every decoded-sample channel of a take as arrays, by topic — the fast way to hand a take to
    the pipeline (a channel whose messages differ in layout is decoded message by message and
    stacked)."""
    import numpy as np

    r = TakeReader(path)
    datas = r.message_data(lambda ch: ch.message_encoding == schemas.MESSAGE_ENCODING)
    classes = schemas.sample_classes()
    out = {}
    for cid, ds in datas.items():
        ch = r.channels.get(cid)
        if ch is None or ch.message_encoding != schemas.MESSAGE_ENCODING:
            continue
        sc = r.schemas[ch.schema_id]
        layout = schemas.parse_definition(sc.name, sc.data.decode(), classes)
        if not ds:
            continue
        cols = schemas.decode_columns(layout, ds)
        if cols is None:
            samples = [schemas.decode(layout, bytes(d)) for d in _split_rows(ds)]
            cols = {}
            for f in layout.fields:
                vals = [getattr(s, f.name) for s in samples]
                same = f.kind in ("str", "strs") and all(v == vals[0] for v in vals)
                cols[f.name] = vals[0] if same else (np.stack(vals) if f.kind == "array" and
                                                     len({np.shape(v) for v in vals}) == 1 else
                                                     np.asarray(vals) if f.kind != "array" else vals)  # fmt: skip
        md = dict(ch.metadata)
        out[ch.topic] = ChannelColumns(ch.topic, md.get("source", ""), md.get("entity", ""), layout.cls.__name__, md,
                                       _count(ds), cols)  # fmt: skip
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

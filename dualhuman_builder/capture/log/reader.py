"""Read takes back, tolerant of damage: check, repair, dump, and the packets and samples for replay.

A take cut off by a crash, ``kill -9`` or a full disk has no index (summary and footer) and may end in
a partial record. :class:`TakeReader` scans the top-level records first (opcode + length, no
payload read), keeps the prefix of complete records, and reads that in file order with the
``mcap`` library's record parsers; a chunk whose CRC or compression is broken is skipped and
reported, never silently used. :func:`check_take` says what a file holds and what is lost;
:func:`~dualhuman_builder.capture.log.repair.repair_take` rewrites it with a full index (the original is
kept beside it).

Every length and count read from the file is checked against the bytes present before anything is
allocated from it: a record's length against the file, a chunk's uncompressed size against
:data:`MAX_CHUNK_BYTES` and what its codec can expand its compressed bytes to, and the
decompressor is never let produce more than the chunk claims. Damage gives a
:class:`~dualhuman_builder.errors.FormatError` or a reported skip, never another exception.

The schemas and channels of a complete take are read from its summary section first, so that a
damaged chunk holding channel records loses only its own messages; what a damaged chunk held is
counted per channel from the message index records written after it.
"""

from __future__ import annotations

import io
import json
import struct
import zlib
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

from mcap.records import Attachment, Channel, Chunk, ChunkIndex, Header, Message, Metadata, Schema, Statistics

from dualhuman_builder.capture.log import schemas
from dualhuman_builder.capture.log.mcapio import OP_CHANNEL, OP_MESSAGE, OP_SCHEMA, iter_chunk_records, message_fields
from dualhuman_builder.capture.sources import RawPacket
from dualhuman_builder.errors import FormatError

MAGIC = b"\x89MCAP0\r\n"
_RECORD_HEAD = struct.Struct("<BQ")
_FOOTER = struct.Struct("<BQQQI")  # opcode, length (20), summary start, summary offset start, summary CRC
_OP_FOOTER = 0x02
_OP_CHUNK = 0x06
_OP_MESSAGE_INDEX = 0x07
_OP_CHUNK_INDEX = 0x08
_OP_STATISTICS = 0x0B
_OP_DATA_END = 0x0F
#: Largest uncompressed chunk a take may hold (the recorder writes chunks of about 1 MiB): a chunk
#: claiming more is reported as damaged, never decompressed.
MAX_CHUNK_BYTES = 64 << 20
#: How many times its compressed size each codec can expand a chunk to at most (LZ4's format
#: cannot exceed about 255; zstd's run-length blocks go far beyond what a real take reaches).
_MAX_RATIO = {"": 1, "lz4": 256, "zstd": 4096}


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
    """A chunk's records, decompressed; ValueError when the chunk is damaged or claims more bytes
    than :data:`MAX_CHUNK_BYTES` or than its codec can expand its compressed bytes to."""
    claim, n, codec = chunk.uncompressed_size, len(chunk.data), chunk.compression
    if codec not in _MAX_RATIO:
        raise ValueError(f"unknown chunk compression {codec!r}")
    if claim > MAX_CHUNK_BYTES:
        raise ValueError(f"chunk claims {claim} bytes uncompressed, over the {MAX_CHUNK_BYTES >> 20} MiB "
                         "a chunk may hold")  # fmt: skip
    if claim > _MAX_RATIO[codec] * n + 64:
        raise ValueError(f"chunk claims {claim} bytes from {n} compressed ({codec or 'none'}): more than it can hold")
    if codec == "":
        data = chunk.data
    elif codec == "lz4":
        import lz4.frame

        data = lz4.frame.LZ4FrameDecompressor().decompress(chunk.data, max_length=claim + 1)
    else:
        import zstandard

        parts, got = [], 0
        with zstandard.ZstdDecompressor().stream_reader(chunk.data) as reader:
            while got <= claim:
                part = reader.read(claim + 1 - got)
                if not part:
                    break
                parts.append(part)
                got += len(part)
        data = b"".join(parts)
    if len(data) != claim:
        raise ValueError(f"chunk decompresses to {'more than ' if len(data) > claim else ''}{len(data)} bytes, "
                         f"its header says {claim}")  # fmt: skip
    if chunk.uncompressed_crc and zlib.crc32(data) != chunk.uncompressed_crc:
        raise ValueError("chunk CRC mismatch")
    return data


def _parse(op: int, body: bytes):
    """A record from its body (in memory: the parsers cannot read past it), with the ``mcap``
    library's record parsers."""
    from mcap.data_stream import ReadDataStream

    stream = ReadDataStream(io.BytesIO(body))
    if op == OP_MESSAGE:
        return Message.read(stream, len(body))
    return {**_CONTENT, _OP_CHUNK_INDEX: ChunkIndex, _OP_STATISTICS: Statistics}[op].read(stream)


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


@dataclass
class TakeSummary:
    """What the summary section of a complete take lists: ``schemas`` and ``channels`` by id, the
    ``chunk_indexes`` and the ``statistics`` (None if absent); ``problems`` met reading it."""

    schemas: dict[int, Schema] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    chunk_indexes: list[ChunkIndex] = field(default_factory=list)
    statistics: Statistics | None = None
    problems: list[str] = field(default_factory=list)


def read_summary(path: str | Path, scan: TakeScan | None = None) -> TakeSummary | None:
    """The summary section of ``path`` (None when the take has no footer or no summary), each
    record parsed on its own from bytes bounded by the file: a damaged record is left out and
    said in ``problems``."""
    path = Path(path)
    scan = scan or scan_take(path)
    if not scan.complete:
        return None
    footer_at = scan.size - len(MAGIC) - _FOOTER.size
    if footer_at < len(MAGIC):
        return None
    with open(path, "rb") as f:
        f.seek(footer_at)
        op, length, start, offsets_at, crc = _FOOTER.unpack(f.read(_FOOTER.size))
        if op != _OP_FOOTER or length != _FOOTER.size - _RECORD_HEAD.size or start == 0:
            return None
        out = TakeSummary()
        end = offsets_at if offsets_at else footer_at
        if not len(MAGIC) <= start <= end <= footer_at:
            out.problems.append(f"the footer points at a summary section outside the file ({start}..{end})")
            return out
        f.seek(start)
        data = f.read(end - start)
        if crc:
            f.seek(end)
            rest = f.read(footer_at + _FOOTER.size - 4 - end)
            if zlib.crc32(data + rest) != crc:
                out.problems.append("summary section CRC mismatch (its records are used where they parse)")
    try:
        for op, body in iter_chunk_records(data):
            if op not in (OP_SCHEMA, OP_CHANNEL, _OP_CHUNK_INDEX, _OP_STATISTICS):
                continue
            try:
                rec = _parse(op, bytes(body))
            except Exception as e:  # noqa: BLE001 - one damaged summary record: say so, read the others
                out.problems.append(f"unreadable summary record (opcode 0x{op:02x}): {type(e).__name__}: {e}")
                continue
            if isinstance(rec, Schema):
                out.schemas[rec.id] = rec
            elif isinstance(rec, Channel):
                out.channels[rec.id] = rec
            elif isinstance(rec, ChunkIndex):
                out.chunk_indexes.append(rec)
            else:
                out.statistics = rec
    except ValueError as e:
        out.problems.append(f"summary section damaged: {e}")
    return out


def message_index_counts(path: str | Path, offset: int, end: int) -> Counter:
    """Messages per channel id listed by the message index records that start at ``offset`` (right
    after a chunk) and follow each other up to ``end``: what that chunk held."""
    out: Counter = Counter()
    with open(path, "rb") as f:
        pos = offset
        while pos + _RECORD_HEAD.size <= end:
            f.seek(pos)
            op, length = _RECORD_HEAD.unpack(f.read(_RECORD_HEAD.size))
            if op != _OP_MESSAGE_INDEX or length < 6 or pos + _RECORD_HEAD.size + length > end:
                break
            body = f.read(length)
            cid, n_bytes = struct.unpack_from("<HI", body, 0)
            out[cid] += min(n_bytes, length - 6) // 16
            pos += _RECORD_HEAD.size + length
    return out


class TakeReader:
    """Records of a take in file order, up to its last complete record.

    ``summary``: the :class:`TakeSummary` of a complete take (None otherwise); its schemas and
    channels are known from the start. ``problems``: what was skipped (bad chunks) or cut off;
    ``schemas`` / ``channels`` by id and ``metadata`` by name fill in while :meth:`records` runs
    (:meth:`load_header` reads them all first). After a full pass, ``lost_bytes`` counts the bytes
    that could not be read (the cut-off tail and every damaged record) and ``lost_messages`` the
    messages per channel id that the damaged chunks' message indexes list."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self.scan = scan_take(self.path)
        self.summary = read_summary(self.path, self.scan)
        self._base_problems: list[str] = []
        if self.scan.tail:
            lost = self.scan.size - self.scan.good_end
            self._base_problems.append(f"file ends in {self.scan.tail} (lost: {lost} bytes)")
        if self.summary is not None:
            self._base_problems += self.summary.problems
        self.problems: list[str] = list(self._base_problems)
        self.schemas: dict[int, Schema] = dict(self.summary.schemas) if self.summary else {}
        self.channels: dict[int, Channel] = dict(self.summary.channels) if self.summary else {}
        self.metadata: dict[str, dict[str, str]] = {}
        self.attachments: list[Attachment] = []
        self.damaged_bytes = 0
        self.lost_messages: Counter = Counter()
        self._unknown: Counter = Counter()
        self._undecodable: Counter = Counter()
        self._layouts: dict[int, schemas.Layout] = {}

    @property
    def lost_bytes(self) -> int:
        """Bytes that could not be read: the cut-off tail and the damaged records met so far."""
        return self.scan.size - self.scan.good_end + self.damaged_bytes

    def lost_per_topic(self) -> Counter:
        """:attr:`lost_messages` by topic (``channel <id>`` where the channel is unknown)."""
        return Counter({(self.channels[c].topic if c in self.channels else f"channel {c}"): n
                        for c, n in self.lost_messages.items()})  # fmt: skip

    def _begin_pass(self) -> None:
        self.problems[:] = self._base_problems
        self.damaged_bytes = 0
        self.lost_messages.clear()
        self._unknown.clear()
        self._undecodable.clear()

    def _end_pass(self) -> None:
        for cid, n in sorted(self._unknown.items()):
            self.problems.append(f"{n} messages on channel {cid}, whose channel record is lost")
        for topic, n in sorted(self._undecodable.items()):
            self.problems.append(f"{topic}: {n} messages do not decode; left out")

    def _damaged(self, pos: int, size: int, what: str, chunk=None) -> None:
        """A damaged record of ``size`` bytes at ``pos``: counted, said, and for a chunk the
        messages its message index records list counted as lost."""
        self.damaged_bytes += size
        lost = Counter()
        if chunk is not None:
            lost = message_index_counts(self.path, pos + size, self.scan.good_end)
            self.lost_messages.update(lost)
            what = f"{what}; it held {sum(lost.values())} messages" if lost else what
        self.problems.append(what)

    def _top(self) -> Iterator[tuple[int, bytes, int]]:
        """``(opcode, body, offset)`` of the top-level records of the data section that carry
        content (header, schemas, channels, messages, chunks, metadata, attachments), in file
        order; index records are skipped by seeking (their content is rebuilt from the data when
        needed)."""
        end = self.scan.good_end
        head = _RECORD_HEAD
        with open(self.path, "rb") as f:
            f.seek(len(MAGIC))
            pos = len(MAGIC)
            while pos + head.size <= end:
                op, length = head.unpack(f.read(head.size))
                if op == _OP_DATA_END or op == _OP_FOOTER or pos + head.size + length > end:
                    return
                if op in _CONTENT:
                    body = f.read(length)
                    if len(body) < length:
                        return
                    yield op, body, pos
                else:
                    f.seek(length, 1)
                pos += head.size + length

    def _items(self) -> Iterator[tuple]:
        """``("msg", channel id, sequence, log time, publish time, data)`` for messages (data a
        memoryview) and ``("rec", record)`` for every other record, in file order."""
        self._begin_pass()
        for op, body, pos in self._top():
            if op == OP_MESSAGE:
                try:
                    fields = message_fields(memoryview(body))
                except ValueError as e:
                    self._damaged(pos, _RECORD_HEAD.size + len(body), f"unreadable message record at byte {pos}: {e}")
                    continue
                yield ("msg", *fields)
                continue
            try:
                rec = _parse(op, body)
            except Exception as e:  # noqa: BLE001 - a damaged record: say so, go on with the next
                what = f"unreadable record (opcode 0x{op:02x}) at byte {pos}: {type(e).__name__}: {e}"
                self._damaged(pos, _RECORD_HEAD.size + len(body), what)
                continue
            if isinstance(rec, Chunk):
                try:
                    items = list(_chunk_items(rec))
                except Exception as e:  # noqa: BLE001 - any decode failure of one chunk: skip it, say so
                    self._damaged(pos, _RECORD_HEAD.size + len(body),
                                  f"skipped a damaged chunk at byte {pos} ({_RECORD_HEAD.size + len(body)} bytes, "
                                  f"{rec.message_start_time}...{rec.message_end_time} ns): {type(e).__name__}: {e}",
                                  chunk=rec)  # fmt: skip
                    continue
                for item in items:
                    if item[0] == "rec":
                        self._note(item[1])
                    yield item
            else:
                self._note(rec)
                yield ("rec", rec)
        self._end_pass()

    def message_data(self, wanted: Callable[[Channel], bool]) -> dict[int, list]:
        """The data of every message on the channels ``wanted`` accepts, per channel id, in file
        order — the fast path (no per-message objects). Each list holds memoryviews of single
        messages and/or 2-D uint8 arrays of equal-length messages, one row per message.

        A complete take is read through its index (the summary's channels and chunk indexes, each
        chunk's message index: gathered with numpy, no per-message Python); a take without an index
        (cut off) by scanning every record."""
        if self.scan.complete and self.summary is not None and self.summary.chunk_indexes and not self.summary.problems:
            try:
                return self._indexed_message_data(wanted)
            except ValueError as e:  # an index we cannot use: scan the records instead
                note = f"index unusable ({e}); records scanned instead"
                out = self._scanned_message_data(wanted)
                self.problems.append(note)
                return out
        return self._scanned_message_data(wanted)

    def _indexed_message_data(self, wanted: Callable[[Channel], bool]) -> dict[int, list]:
        import numpy as np

        def windows(buf, width: int):
            """Every ``width``-byte window of ``buf`` as rows of a read-only view (no copy)."""
            return np.ndarray((len(buf) - width + 1, width), dtype=np.uint8, buffer=buf, strides=(1, 1))

        self._begin_pass()
        head = _RECORD_HEAD
        keep = {cid for cid, ch in self.channels.items() if wanted(ch)}
        out: dict[int, list] = {cid: [] for cid in keep}
        size = self.scan.size
        with open(self.path, "rb") as f:

            def record(offset: int, opcode: int) -> bytes:
                if offset < len(MAGIC) or offset + head.size > size:
                    raise ValueError(f"the index points outside the file (byte {offset})")
                f.seek(offset)
                op, length = head.unpack(f.read(head.size))
                if op != opcode or offset + head.size + length > size:
                    raise ValueError(f"the index points at a record of opcode 0x{op:02x} and {length} bytes "
                                     f"at byte {offset}")  # fmt: skip
                return f.read(length)

            for ci in sorted(self.summary.chunk_indexes, key=lambda c: c.chunk_start_offset):
                body = record(ci.chunk_start_offset, _OP_CHUNK)
                chunk = None
                try:
                    chunk = _parse(_OP_CHUNK, body)
                    data = _decompress(chunk)
                except Exception as e:  # noqa: BLE001 - one damaged chunk: skip it, say so, count what it held
                    size = head.size + len(body)
                    self._damaged(ci.chunk_start_offset, size,
                                  f"skipped a damaged chunk at byte {ci.chunk_start_offset} ({size} bytes, "
                                  f"{ci.message_start_time}...{ci.message_end_time} ns): {type(e).__name__}: {e}",
                                  chunk=ci)  # fmt: skip
                    continue
                u8 = np.frombuffer(data, dtype=np.uint8)
                for cid, off in ci.message_index_offsets.items():
                    if cid not in keep:
                        continue
                    body = record(off, _OP_MESSAGE_INDEX)
                    if len(body) < 6:
                        raise ValueError("bad message index record")
                    n_bytes = struct.unpack_from("<I", body, 2)[0]
                    if 6 + n_bytes > len(body) or n_bytes % 16:
                        raise ValueError("message index longer than its record")
                    offsets = np.frombuffer(body, dtype="<u8", count=n_bytes // 8, offset=6)[1::2]
                    offsets = np.sort(offsets.astype(np.int64))
                    if len(offsets) == 0:
                        continue
                    if offsets[0] < 0 or offsets[-1] + 31 > len(data):
                        raise ValueError("message index offset outside the chunk")
                    channel = windows(u8, 2)[offsets + 9].copy().view("<u2").ravel()
                    if (u8[offsets] != OP_MESSAGE).any() or (channel != cid).any():
                        raise ValueError(f"message index of channel {cid} points at other records")
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
        out: dict[int, list] = {cid: [] for cid, ch in self.channels.items() if wanted(ch)}
        for item in self._items():
            if item[0] == "msg":
                data = out.get(item[1])
                if data is not None:
                    data.append(item[5])
                elif item[1] not in self.channels:
                    self._unknown[item[1]] += 1
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
        """``(channel, message)`` in file order (message data as a memoryview); messages on a
        channel whose record is lost are counted in :attr:`problems`."""
        channels = self.channels
        for item in self._items():
            if item[0] != "msg":
                continue
            ch = channels.get(item[1])
            if ch is None:
                self._unknown[item[1]] += 1
                continue
            yield ch, _Msg(item[1], item[2], item[3], item[4], item[5])

    # ------------------------------------------------------------------ take contents
    def layout(self, ch: Channel) -> schemas.Layout:
        """The sample layout of decoded-sample channel ``ch``; FormatError when its schema is lost
        or is not one of ours."""
        out = self._layouts.get(ch.id)
        if out is None:
            sc = self.schemas.get(ch.schema_id)
            if sc is None:
                raise FormatError(f"channel {ch.topic!r}: its schema (id {ch.schema_id}) is lost", path=self.path,
                                  fix="`dualhuman log repair` re-decodes its samples from the raw bytes")  # fmt: skip
            try:
                text = bytes(sc.data).decode()
            except UnicodeDecodeError:
                raise FormatError(f"schema {sc.name!r} is not text", path=self.path) from None
            out = self._layouts[ch.id] = schemas.parse_definition(sc.name, text, schemas.sample_classes())
        return out

    def take_meta(self) -> dict[str, Any]:
        """The ``take`` metadata (sources and bindings parsed from JSON); FormatError when they are
        not JSON."""
        meta = dict(self.metadata.get("take", {}))
        for k in ("sources", "bindings"):
            if k in meta:
                try:
                    meta[k] = json.loads(meta[k])
                except ValueError as e:
                    raise FormatError(f"the take's metadata {k!r} is not JSON ({e})", path=self.path) from None
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
        """``(source name, sample)`` for every decoded sample, in recorded order; a message that
        does not decode, or whose schema is lost, is counted in :attr:`problems` and left out."""
        for ch, msg in self.messages():
            if ch.message_encoding != schemas.MESSAGE_ENCODING:
                continue
            try:
                sample = schemas.decode(self.layout(ch), msg.data)
            except FormatError:
                self._undecodable[ch.topic] += 1
                continue
            yield ch.metadata.get("source", ""), sample


@dataclass
class ChannelColumns:
    """All decoded samples of one channel as arrays: ``columns[field]`` has the samples along
    axis 0 (``(N,)`` for scalars, ``(N, *shape)`` for arrays; strings: the one shared value).

    A channel whose layout changes (an MVN prop added mid-take) is merged by name, as
    :func:`~dualhuman_builder.capture.log.schemas.decode_channel` says: ``segment_names`` is then
    the union (the most common list first) and ``segment_names__present (N, U)`` says which
    segments each sample carried, absent values NaN. ``odd``: samples laid out otherwise than the
    channel's most common layout; ``skipped``: messages that do not decode, left out."""

    topic: str
    source: str
    entity: str
    sample_type: str
    metadata: dict[str, str]
    count: int
    columns: dict[str, Any]
    odd: int = 0
    skipped: int = 0


def _count(parts: list) -> int:
    return sum(len(p) if getattr(p, "ndim", 1) == 2 else 1 for p in parts)


def read_columns(path: str | Path, problems: list[str] | None = None) -> dict[str, ChannelColumns]:
    """Every decoded-sample channel of a take as arrays, by topic — the fast way to hand a take to
    the pipeline (messages of one layout are gathered in one ``frombuffer``; a channel whose layout
    changes is merged by name, see :class:`ChannelColumns`). What could not be read (damaged
    chunks, messages that do not decode, channels whose schema is lost) is appended to
    ``problems`` when given."""
    r = TakeReader(path)
    datas = r.message_data(lambda ch: ch.message_encoding == schemas.MESSAGE_ENCODING)
    out = {}
    for cid, ds in datas.items():
        ch = r.channels.get(cid)
        if ch is None or ch.message_encoding != schemas.MESSAGE_ENCODING or not ds:
            continue
        try:
            layout = r.layout(ch)
        except FormatError as e:
            r.problems.append(f"{ch.topic}: {e.message}; its {_count(ds)} messages left out")
            continue
        got = schemas.decode_channel(layout, ds)
        if got.skipped:
            r.problems.append(f"{ch.topic}: {got.skipped} messages do not decode; left out")
        if not got.count:
            continue
        md = dict(ch.metadata)
        out[ch.topic] = ChannelColumns(ch.topic, md.get("source", ""), md.get("entity", ""), layout.cls.__name__, md,
                                       got.count, got.columns, got.odd, got.skipped)  # fmt: skip
    if problems is not None:
        problems.extend(r.problems)
    return out


# ---------------------------------------------------------------------- check and repair
@dataclass
class CheckReport:
    """What :func:`check_take` found. ``lost_bytes``: bytes that could not be read (a cut-off
    tail and damaged records); ``lost_messages``: messages per topic that damaged chunks held,
    where their message indexes say."""

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
    lost_messages: Counter = field(default_factory=Counter)

    @property
    def ok(self) -> bool:
        """Complete and nothing skipped."""
        return self.complete and not self.problems

    def to_dict(self) -> dict[str, Any]:
        return {"path": str(self.path), "ok": self.ok, "complete": self.complete, "size": self.size,
                "readable_bytes": self.readable_bytes, "lost_bytes": self.lost_bytes, "chunks": self.chunks,
                "messages": self.messages, "per_topic": dict(self.per_topic), "metadata": self.metadata,
                "problems": self.problems, "first_ns": self.first_ns, "last_ns": self.last_ns,
                "duration_s": None if self.first_ns is None else (self.last_ns - self.first_ns) / 1e9,
                "lost_messages": dict(self.lost_messages)}  # fmt: skip


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
    return CheckReport(r.path, r.scan.size, r.scan.complete, r.scan.good_end, r.lost_bytes, r.scan.chunks, n, per_topic,
                       sorted(r.metadata), list(r.problems), first, last, r.lost_per_topic())  # fmt: skip


# ---------------------------------------------------------------------- dump
def _jsonable(v):
    import numpy as np

    if isinstance(v, np.ndarray):
        return v.tolist()
    if isinstance(v, tuple):
        return list(v)
    return v


def dump_jsonl(path: str | Path, out, *, raw: bool = False, topics: tuple[str, ...] = (),
               problems: list[str] | None = None) -> int:  # fmt: skip
    """Write every decoded sample of a take as one JSON object per line to ``out`` (a text
    stream): ``topic``, ``source``, ``entity``, ``actor`` (when bound), ``type``, then the sample's
    fields (SI units: metres, m/s, rad/s, m/s^2; quaternions x, y, z, w; times int ns). ``raw``
    also writes the raw packets (``data_hex``). ``topics``: only topics starting with one of these.
    Messages that do not decode are left out, and with the damage met appended to ``problems``
    (when given). Returns the number of lines."""
    r = TakeReader(path)
    n = 0
    for ch, msg in r.messages():
        if topics and not ch.topic.startswith(topics):
            continue
        md = ch.metadata
        if ch.message_encoding == schemas.MESSAGE_ENCODING:
            try:
                layout = r.layout(ch)
                sample = schemas.decode(layout, msg.data)
            except FormatError:
                r._undecodable[ch.topic] += 1
                continue
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
    if problems is not None:
        problems.extend(r.problems)
    return n

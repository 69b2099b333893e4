"""The per-message hot paths of MCAP writing and reading, around the ``mcap`` library.

The ``mcap`` library writes the file structure (header, schemas, channels, metadata, chunk
records, message indexes, summary, footer) and we keep it for that. Its per-message path builds a
record object and several small writes per message (about 10 us each on this class of CPU), too
slow for a studio at 20x real time, so :class:`FastWriter` replaces only that path: a message
record is appended to the chunk buffer as one ``struct.pack`` (opcode 0x05, length, channel id,
sequence, log time, publish time) plus its data, and indexed as the library does. Everything is
written in the MCAP format the library defines; the tests read our files back with the library's
own indexed reader.

:func:`iter_chunk_records` is the reading counterpart: the records inside a decompressed chunk,
as ``(opcode, memoryview)`` with lengths checked against the bytes present.
"""

from __future__ import annotations

import struct
from io import BytesIO
from typing import Iterator

from mcap.data_stream import RecordBuilder
from mcap.records import Channel, MessageIndex, Schema
from mcap.writer import Writer

OP_MESSAGE = 0x05
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log time, publish time
_MESSAGE_FIXED = 22
_RECORD = struct.Struct("<BQ")


class FastChunkBuilder:
    """Drop-in for ``mcap``'s ChunkBuilder (the attributes and methods its Writer uses), with a
    one-write message path."""

    def __init__(self) -> None:
        self._buf = BytesIO()
        self.message_indices: dict[int, MessageIndex] = {}
        self.message_start_time = 0
        self.message_end_time = 0
        self.num_messages = 0

    @property
    def count(self) -> int:
        return self._buf.tell()

    def end(self) -> bytes:
        data = self._buf.getvalue()
        self._buf = BytesIO()
        return data

    def _record(self, record) -> None:
        rb = RecordBuilder()
        record.write(rb)
        self._buf.write(rb.end())

    def add_channel(self, channel: Channel) -> None:
        self._record(channel)

    def add_schema(self, schema: Schema) -> None:
        self._record(schema)

    def add(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        buf = self._buf
        offset = buf.tell()
        buf.write(_MESSAGE_HEAD.pack(OP_MESSAGE, _MESSAGE_FIXED + len(data), channel_id, sequence, log_time,
                                     publish_time))  # fmt: skip
        buf.write(data)
        if self.num_messages == 0:
            self.message_start_time = self.message_end_time = log_time
        elif log_time < self.message_start_time:
            self.message_start_time = log_time
        elif log_time > self.message_end_time:
            self.message_end_time = log_time
        index = self.message_indices.get(channel_id)
        if index is None:
            index = self.message_indices[channel_id] = MessageIndex(channel_id=channel_id, records=[])
        index.records.append((log_time, offset))
        self.num_messages += 1

    def add_message(self, message) -> None:
        self.add(message.channel_id, message.log_time, message.data, message.publish_time, message.sequence)

    def reset(self) -> None:
        self.message_indices = {}
        self.message_start_time = self.message_end_time = 0
        self.num_messages = 0
        self._buf = BytesIO()


class FastWriter(Writer):
    """``mcap.writer.Writer`` with :meth:`add_message` on the fast path (same file, same
    statistics). Chunked writing only."""

    def __init__(self, output, **kwargs):
        super().__init__(output, **kwargs)
        if getattr(self, "_Writer__chunk_builder", None) is None or not hasattr(self, "_Writer__statistics"):
            raise RuntimeError("this mcap version's Writer has an unexpected layout; pin mcap to a tested release")
        self._chunks = FastChunkBuilder()
        self._Writer__chunk_builder = self._chunks
        self._stats = self._Writer__statistics
        self._limit = kwargs.get("chunk_size", 1024 * 1024)
        self._finalize = self._Writer__finalize_chunk

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        st = self._stats
        if st.message_count == 0:
            st.message_start_time = st.message_end_time = log_time
        elif log_time < st.message_start_time:
            st.message_start_time = log_time
        elif log_time > st.message_end_time:
            st.message_end_time = log_time
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        chunks = self._chunks
        chunks.add(channel_id, log_time, data, publish_time, sequence)
        if chunks._buf.tell() > self._limit:
            self._finalize()


def iter_chunk_records(data: bytes) -> Iterator[tuple[int, memoryview]]:
    """``(opcode, body)`` of each record in a decompressed chunk; raises ValueError when a length
    runs past the end (a damaged chunk)."""
    mv = memoryview(data)
    n = len(mv)
    pos = 0
    unpack = _RECORD.unpack_from
    while pos < n:
        if pos + 9 > n:
            raise ValueError(f"chunk ends inside a record header at byte {pos}")
        op, length = unpack(mv, pos)
        start = pos + 9
        end = start + length
        if end > n:
            raise ValueError(f"record of {length} bytes at byte {pos} runs past the chunk's {n} bytes")
        yield op, mv[start:end]
        pos = end


_MESSAGE_BODY = struct.Struct("<HIQQ")


def message_fields(body: memoryview) -> tuple[int, int, int, int, memoryview]:
    """``(channel id, sequence, log time, publish time, data)`` of a message record body."""
    if len(body) < _MESSAGE_FIXED:
        raise ValueError(f"message record of {len(body)} bytes is shorter than its {_MESSAGE_FIXED}-byte head")
    ch, seq, lt, pt = _MESSAGE_BODY.unpack_from(body, 0)
    return ch, seq, lt, pt, body[_MESSAGE_FIXED:]

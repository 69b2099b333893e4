"""The per-message hot paths of MCAP writing and reading, around the ``mcap`` library.

The ``mcap`` library writes the file structure (header, schemas, channels, metadata, chunk
records, message indexes, summary, footer) and we keep it for that. Its per-message path builds a
record object and several small writes per message (about 10 us each on this class of CPU), too
slow for a studio at 20x real time, so :class:`FastWriter` replaces only that path: a message
record is appended to the chunk buffer as one ``struct.pack`` (opcode 0x05, length, channel id,
sequence, log time, publish time) plus its data; its message-index entry and the statistics are
computed per chunk with numpy. Everything is
written in the MCAP format the library defines; the tests read our files back with the library's
own indexed reader.

:func:`iter_chunk_records` is the reading counterpart: the records inside a decompressed chunk,
as ``(opcode, memoryview)`` with lengths checked against the bytes present.
"""

from __future__ import annotations

import struct
from typing import Iterator

from mcap.data_stream import RecordBuilder
import numpy as np
from mcap.records import Channel, Schema
from mcap.writer import Writer

OP_MESSAGE = 0x05
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
OP_MESSAGE_INDEX = 0x07
_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, record length, channel id, byte length of the (time, offset) pairs
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")  # opcode, record length, channel, sequence, log time, publish time
_MESSAGE_FIXED = 22
_RECORD = struct.Struct("<BQ")


class _MessageIndex:
    """A chunk's message index for one channel, written in one piece (the library writes each
    (time, offset) pair with two separate calls)."""

    def __init__(self, channel_id: int, times: np.ndarray, offsets: np.ndarray):
        self.channel_id = channel_id
        self.records = np.stack([times, offsets], axis=1).astype("<u8")

    def write(self, stream) -> None:
        body = self.records.tobytes()
        stream.write(_INDEX_HEAD.pack(OP_MESSAGE_INDEX, 6 + len(body), self.channel_id, len(body)) + body)


class FastChunkBuilder:
    """Drop-in for ``mcap``'s ChunkBuilder (the attributes and methods its Writer uses). A message
    costs one ``struct.pack``, two buffer appends and three list appends; its index entry, the
    chunk's time range and the file statistics are computed once per chunk, with numpy, when the
    Writer finalises the chunk (:meth:`end`)."""

    def __init__(self, statistics=None) -> None:
        self._buf = bytearray()
        self._ch: list[int] = []
        self._t: list[int] = []
        self._off: list[int] = []
        self._stats = statistics
        self._indices: dict[int, _MessageIndex] | None = None

    @property
    def count(self) -> int:
        return len(self._buf)

    @property
    def num_messages(self) -> int:
        return len(self._ch)

    @property
    def message_start_time(self) -> int:
        return min(self._t) if self._t else 0

    @property
    def message_end_time(self) -> int:
        return max(self._t) if self._t else 0

    @property
    def message_indices(self) -> dict[int, _MessageIndex]:
        if self._indices is None:
            self._indices = {}
            if self._ch:
                ch = np.asarray(self._ch, dtype=np.int64)
                t = np.asarray(self._t, dtype=np.uint64)
                off = np.asarray(self._off, dtype=np.uint64)
                order = np.argsort(ch, kind="stable")
                ids, starts = np.unique(ch[order], return_index=True)
                for cid, a, b in zip(ids.tolist(), starts.tolist(), [*starts[1:].tolist(), len(order)]):
                    sel = order[a:b]
                    self._indices[cid] = _MessageIndex(cid, t[sel], off[sel])
        return self._indices

    def end(self) -> bytes:
        self._count_statistics()
        data = bytes(self._buf)
        self._buf = bytearray()
        return data

    def _count_statistics(self) -> None:
        st = self._stats
        if st is None or not self._ch:
            return
        for cid, index in self.message_indices.items():
            st.channel_message_counts[cid] += len(index.records)
        n = len(self._ch)
        lo, hi = self.message_start_time, self.message_end_time
        if st.message_count == 0:
            st.message_start_time, st.message_end_time = lo, hi
        else:
            st.message_start_time = min(st.message_start_time, lo)
            st.message_end_time = max(st.message_end_time, hi)
        st.message_count += n

    def _record(self, record) -> None:
        rb = RecordBuilder()
        record.write(rb)
        self._buf += rb.end()

    def add_channel(self, channel: Channel) -> None:
        self._record(channel)

    def add_schema(self, schema: Schema) -> None:
        self._record(schema)

    def add(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        buf = self._buf
        self._off.append(len(buf))
        buf += _MESSAGE_HEAD.pack(OP_MESSAGE, _MESSAGE_FIXED + len(data), channel_id, sequence, log_time, publish_time)
        buf += data
        self._ch.append(channel_id)
        self._t.append(log_time)

    def add_message(self, message) -> None:
        self.add(message.channel_id, message.log_time, message.data, message.publish_time, message.sequence)

    def reset(self) -> None:
        self._buf = bytearray()
        self._ch, self._t, self._off = [], [], []
        self._indices = None


class FastWriter(Writer):
    """``mcap.writer.Writer`` with :meth:`add_message` on the fast path (same file, same
    statistics, counted per chunk). Chunked writing only."""

    def __init__(self, output, **kwargs):
        super().__init__(output, **kwargs)
        if getattr(self, "_Writer__chunk_builder", None) is None or not hasattr(self, "_Writer__statistics"):
            raise RuntimeError("this mcap version's Writer has an unexpected layout; pin mcap to a tested release")
        self._chunks = FastChunkBuilder(self._Writer__statistics)
        self._Writer__chunk_builder = self._chunks
        self._limit = kwargs.get("chunk_size", 1024 * 1024)
        self._finalize = self._Writer__finalize_chunk

    def add_message(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int = 0) -> None:
        chunks = self._chunks
        chunks.add(channel_id, log_time, data, publish_time, sequence)
        if len(chunks._buf) > self._limit:
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

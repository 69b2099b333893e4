"""The record-level path of MCAP reading, beside the ``mcap`` library.

Take files are written with the library's public ``mcap.writer.Writer`` (:mod:`.writer`).
:mod:`.reader` walks decompressed chunks itself, so that a damaged chunk is reported rather than
trusted and a message costs no record object: :func:`iter_chunk_records` yields a chunk's records
as ``(opcode, memoryview)`` with lengths checked against the bytes present, and
:func:`message_fields` splits a message record's body.
"""

from __future__ import annotations

import struct
from typing import Iterator

OP_MESSAGE = 0x05
OP_SCHEMA = 0x03
OP_CHANNEL = 0x04
_MESSAGE_FIXED = 22  # channel id, sequence, log time, publish time
_RECORD = struct.Struct("<BQ")
_MESSAGE_BODY = struct.Struct("<HIQQ")


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


def message_fields(body: memoryview) -> tuple[int, int, int, int, memoryview]:
    """``(channel id, sequence, log time, publish time, data)`` of a message record body."""
    if len(body) < _MESSAGE_FIXED:
        raise ValueError(f"message record of {len(body)} bytes is shorter than its {_MESSAGE_FIXED}-byte head")
    ch, seq, lt, pt = _MESSAGE_BODY.unpack_from(body, 0)
    return ch, seq, lt, pt, body[_MESSAGE_FIXED:]

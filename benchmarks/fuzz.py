"""Fuzz every capture decoder and file reader with mutated real inputs: inputs tried, exceptions that escape (goal 0)
and the peak memory of each target's process.

Targets (``--targets``, all by default), each in worker processes of its own:

============  ==========================================================================================
``mvn``       ``mvn+udp://`` decoder (:func:`~dualhuman_builder.capture.sources.make_decoder`)
``vive``      ``vive+udp://`` decoder
``xbus``      ``xbus://`` decoder (serial reads: the frames re-cut at random)
``mti-can``   ``mti+can://`` decoder (16-byte SocketCAN frames)
``vive-usb``  ``vive+usb://`` decoder (52-byte HID IMU reports)
``take``      the take reader: ``TakeReader`` raw packets and take metadata of every input, and of each
              one of ``read_columns``, ``check_take``, ``TakeReader.samples``, ``dump_jsonl``,
              ``repair_take`` (and a check of the repaired file), in turn (:attr:`TakeTarget.SOME`)
``mvnx``      the MVNX importer (``read_mvnx`` and the extras ``import`` stores)
``bvh``       the BVH importer (``read_bvh``, Y-up and Z-up)
``export``    ``export verify`` (:func:`~dualhuman_builder.export.verify.verify_export`) on a small export
              with one member, the manifest or the schema mutated
``annotate``  ``annotate import`` of mutated CSV and JSON Lines files into a workspace (and, every 100
              inputs, ``annotate export``)
============  ==========================================================================================

The inputs grow from a corpus made once by the real encoders and writers and cached in ``benchmarks/cache/fuzz/``:
the simulated studio's packets of every device (a handshake, its suits, trackers and both IMUs), a small take
written by the take writer, small MVNX and BVH files, a one-sequence dataset export and annotation files. A decoder
input is a stream of packets (1 to 128, or a flood of one) cut from the corpus and mutated: random bytes, bit flips,
fields and counters set to extremes, NaN and infinite values, truncation, insertion, repetition, splicing,
another protocol's packets, dropped, repeated, reordered packets and host times that jump or run backwards. One
decoder lives for :data:`SESSION` inputs, as through a take, then ``finish()`` ends it. A file input is the file
mutated the same way at byte level, and along its structure: MCAP records and chunks rebuilt around mutated
contents (valid CRC or none), XML attributes, BVH tokens, JSON values (hostile paths, deep nesting, wrong types),
CSV cells (over-long, control characters).

Escaped: any exception out of a decoder's ``feed``, ``status`` or ``finish``; for a file reader any exception that
is not a :class:`~dualhuman_builder.errors.DualhumanError` (those are the clear errors). An operation over
``--input-timeout`` seconds counts as escaped (a hang), and so does a worker that dies. For a decoder the exceptions
its guard caught and counted (``decoder_errors``: nothing escapes, but the packet is lost) are counted too, with
where they were raised. Each worker's address space is capped at its size after set-up plus ``--memory-mib``, so a
runaway allocation is a ``MemoryError`` (escaped), not a dead machine; the peak memory is the workers' ``ru_maxrss``.
Input ``i`` of target ``T`` is a function of ``--seed``, ``T``, ``i`` and the corpus (the results file records its
SHA-256s), so a run repeats exactly; the corpus is the same when made again, but for the take's clock metadata.

    .venv/bin/python benchmarks/fuzz.py                    # 100,000 inputs per target
    .venv/bin/python benchmarks/fuzz.py --quick            # 1,000 per target, a smoke run
    .venv/bin/python benchmarks/fuzz.py --targets take,xbus --inputs 5000 --out /tmp/fuzz.json
    .venv/bin/python benchmarks/fuzz.py --replay benchmarks/cache/fuzz-findings/xbus/000000-01-feed-TypeError.json

Writes ``benchmarks/results/fuzz.json``; each kind of escape keeps a reproducer (the input, and a ``.json`` that
says how it failed) under ``benchmarks/cache/fuzz-findings/<target>/``, which ``--replay`` runs again.
"""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import math
import mmap
import os
import random
import re
import resource
import selectors
import shutil
import signal
import struct
import subprocess
import sys
import tempfile
import time
import traceback
import warnings
import zlib
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from results_file import Goal, Table, write_results  # noqa: E402

CACHE = ROOT / "benchmarks" / "cache"
CORPUS = CACHE / "fuzz" / "corpus-v1"
FINDINGS = CACHE / "fuzz-findings"
DEFAULT_INPUTS = 100_000
QUICK_INPUTS = 1_000
#: Goal and cap: MiB a target's process may grow beyond its size after set-up.
MEMORY_MIB = 1024
INPUT_TIMEOUT_S = 10.0
#: Decoder inputs fed to one decoder before ``finish()`` (a take's worth of streams).
SESSION = 200
#: Inputs per worker process (a multiple of SESSION): the unit the workers share out.
SHARD = 25_000
#: Distinct escapes per target and worker whose input is saved as a reproducer.
KEEP = 5
#: Distinct escapes per target listed in the results file.
LISTED = 30

DECODERS = {"mvn": "mvn+udp://127.0.0.1:9763", "vive": "vive+udp://127.0.0.1:8051", "xbus": "xbus://loop",
            "mti-can": "mti+can://virtual/ch0", "vive-usb": "vive+usb://"}  # fmt: skip
READERS = ("take", "mvnx", "bvh", "export", "annotate")
TARGETS = (*DECODERS, *READERS)


class InputTimeout(BaseException):
    """One operation on one input ran past ``--input-timeout`` (raised from SIGALRM; a BaseException so that
    the code under test does not swallow it with ``except Exception``)."""


def _alarm(signum, frame):
    raise InputTimeout("no result within the input time limit")


# =============================================================================================== mutation
INTS = {1: (0, 1, 0x7F, 0x80, 0xFE, 0xFF), 2: (0, 1, 0x7FFF, 0x8000, 0xFFFE, 0xFFFF),
        4: (0, 1, 0x7FFFFFFF, 0x80000000, 0xFFFFFFFE, 0xFFFFFFFF),
        8: (0, 1, 2**31, 2**32, 2**63 - 1, 2**63, 2**64 - 2, 2**64 - 1)}  # fmt: skip
FLOATS = (math.nan, -math.nan, math.inf, -math.inf, 0.0, -0.0, 1e308, -1e308, 5e-324, 3.4e38, 1e10, 2.0)
FLOATS32 = (math.nan, -math.nan, math.inf, -math.inf, 0.0, -0.0, 3.4e38, -3.4e38, 1e-45, 1e10, 2.0)
NUMBERS = (b"0", b"-0", b"1", b"-1", b"nan", b"NaN", b"inf", b"-inf", b"1e309", b"-1e309", b"1e-400", b"2147483647",
           b"2147483648", b"-2147483649", b"4294967296", b"9223372036854775808", b"99999999999999999999999", b"1e9",
           b"3.5", b"0x1F", b"", b" ", b"1,5", b"+7", b"1e", b"--1", "\u0661".encode(), b"1" * 5000)  # fmt: skip
#: A field: (byte offset, size in bytes, big-endian).
Field = tuple[int, int, bool]


def set_int(b: bytearray, off: int, size: int, value: int, big: bool) -> None:
    b[off:off + size] = (value & ((1 << 8 * size) - 1)).to_bytes(size, "big" if big else "little")


def mutate_bytes(rng: random.Random, data: bytes, *, fields: list[Field] = (), floats: list[tuple[int, str]] = (),
                 big: bool = False, pool: list[bytes] = (), rounds: int | None = None) -> bytes:  # fmt: skip
    """``data`` after 1 to 8 random mutations: bit flips, extreme bytes, a field (or any aligned integer) set to an
    extreme, a nearby or a random value, a float at ``floats`` (offset, struct format) set to NaN/inf/huge,
    truncation, deletion, insertion, repetition, splicing with a ``pool`` item, random overwrite."""
    b = bytearray(data)
    for _ in range(rounds or rng.choice((1, 1, 1, 2, 2, 3, 4, 8))):
        r = rng.random()
        n = len(b)
        if r < 0.16 and n:
            for _ in range(rng.randint(1, 4)):
                b[rng.randrange(n)] ^= 1 << rng.randrange(8)
        elif r < 0.24 and n:
            b[rng.randrange(n)] = rng.choice(INTS[1]) if rng.random() < 0.7 else rng.randrange(256)
        elif r < 0.46:
            if fields and rng.random() < 0.8:
                off, size, fbig = rng.choice(fields)
            else:
                size = rng.choice((1, 2, 4, 8))
                off, fbig = rng.randrange(max(1, n - size + 1)), big if rng.random() < 0.8 else not big
            if off + size > n:
                continue
            old = int.from_bytes(b[off:off + size], "big" if fbig else "little")
            c = rng.random()
            value = (rng.choice(INTS[size]) if c < 0.5 else old + rng.choice((-1, 1, -2, 2, 7, -128, 1 << 8 * size - 1))
                     if c < 0.8 else rng.getrandbits(8 * size))  # fmt: skip
            set_int(b, off, size, value, fbig)
        elif r < 0.54 and floats:
            off, fmt = rng.choice(floats)
            if off + struct.calcsize(fmt) <= n:
                struct.pack_into(fmt, b, off, rng.choice(FLOATS32 if fmt.endswith("f") else FLOATS))
        elif r < 0.62:
            del b[rng.randrange(n + 1):]
        elif r < 0.68 and n:
            i = rng.randrange(n)
            del b[i:i + rng.randint(1, 64)]
        elif r < 0.75:
            i = rng.randrange(n + 1)
            b[i:i] = rng.randbytes(rng.choice((1, 2, 4, 8, 16, 64, 256)))
        elif r < 0.82 and n:
            i = rng.randrange(n)
            b[i:i] = b[i:i + rng.randint(1, 64)] * rng.choice((1, 2, 8, 64))
        elif r < 0.92 and pool:
            o = rng.choice(pool)
            i, j = rng.randrange(n + 1), rng.randrange(len(o) + 1)
            b = b[:i] + bytearray(o[j:]) if rng.random() < 0.5 else bytearray(o[:j]) + b[i:]
        elif n:
            i = rng.randrange(n)
            k = rng.randint(1, 32)
            b[i:i + k] = rng.randbytes(k)
    return bytes(b)


# ---------------------------------------------------------------------------------------------- protocols
class Protocol:
    """Structure of one decoder's packets: fields worth setting to extremes, float offsets, a fix-up that makes a
    mutated packet pass the cheap checks (length fields, checksums) so that the deeper code sees it, and
    protocol-specific mutations."""

    big = False
    size: int | None = None  # fixed packet size, if any

    def fields(self, p: bytes) -> list[Field]:
        return []

    def floats(self, p: bytes) -> list[tuple[int, str]]:
        return []

    def fixup(self, rng: random.Random, b: bytes) -> bytes:
        if self.size is not None and len(b) != self.size and rng.random() < 0.7:
            b = b[:self.size].ljust(self.size, b"\0")
        return b

    def special(self, rng: random.Random, b: bytes) -> bytes:
        return b

    def mutate(self, rng: random.Random, p: bytes, pool: list[bytes]) -> bytes:
        if rng.random() < 0.25:
            b = self.special(rng, p)
            if rng.random() < 0.5:
                return b
            p = b
        b = mutate_bytes(rng, p, fields=self.fields(p), floats=self.floats(p), big=self.big, pool=pool)
        return self.fixup(rng, b) if rng.random() < 0.8 else b


class Mvn(Protocol):
    big = True
    HEAD: list[Field] = [(4, 1, True), (5, 1, True), (6, 4, True), (10, 1, True), (11, 1, True), (12, 4, True),
                         (16, 1, True), (17, 1, True), (18, 1, True), (19, 1, True), (20, 2, True), (22, 2, True)]  # fmt: skip
    TYPES = (b"01", b"02", b"03", b"10", b"12", b"13", b"20", b"21", b"22", b"23", b"24", b"25", b"99", b"00")

    def fields(self, p):
        out = list(self.HEAD)
        if p[4:6] == b"02":
            out += [(24 + 32 * k, 4, True) for k in range(min(len(p) // 32, 6))]
        return out

    def floats(self, p):
        if p[4:6] in (b"02", b"21", b"22", b"24"):
            return [(24 + 32 * k + 4 + 4 * j, ">f") for k in range(min(len(p) // 32, 4)) for j in range(7)]
        return []

    def fixup(self, rng, b):
        if len(b) >= 24 and len(b) - 24 <= 0xFFFF:
            b = bytearray(b)
            struct.pack_into(">H", b, 22, len(b) - 24)
            b = bytes(b)
        return b

    def special(self, rng, p):
        b = bytearray(p)
        if len(b) < 24:
            return p
        r = rng.random()
        if r < 0.3:  # another message type, its size made consistent
            b[4:6] = rng.choice(self.TYPES)
            if rng.random() < 0.5:
                b[24:] = rng.randbytes(rng.choice((0, 4, 12, 16, 32, 44, 68, 96, 320, 1400)))
        elif r < 0.55 and p[4:6] == b"02":  # one segment more or fewer (a prop added mid-take)
            if rng.random() < 0.6:
                seg = rng.choice((24, 25, 28, 0, -1, 67, 255, 2**31 - 1))
                b += struct.pack(">i7f", seg, 0.1, 0.2, 0.3, 1.0, 0.0, 0.0, 0.0)
                b[11] = (b[11] + 1) & 0xFF
                k = rng.choice((17, 18))
                b[k] = min(b[k] + 1, 255)
            elif len(b) >= 56:
                del b[-32:]
                b[11] = (b[11] - 1) & 0xFF
        elif r < 0.75:  # another character, or another piece of a split message
            b[rng.choice((10, 16))] = rng.choice((0, 1, 2, 0x7F, 0x80, 0x81, 0xFF, rng.randrange(256)))
        else:  # counters far apart, jumping back
            set_int(b, rng.choice((6, 12)), 4, rng.choice((0, 1, 2**31, 2**32 - 1, rng.getrandbits(32))), True)
        return self.fixup(rng, bytes(b))


class Vive(Protocol):
    size = 128
    FIELDS: list[Field] = [(4, 1, False), (5, 1, False), (6, 2, False), (40, 8, False), (40, 4, False)]
    FLOATS = [(48 + 8 * k, "<d") for k in range(7)] + [(104 + 4 * k, "<f") for k in range(6)]

    def fields(self, p):
        return self.FIELDS

    def floats(self, p):
        return self.FLOATS

    def special(self, rng, p):
        b = bytearray(p.ljust(128, b"\0"))
        r = rng.random()
        if r < 0.5:  # an invented serial
            serial = rng.choice((f"LHR-{rng.getrandbits(32):08X}".encode(), b"", b"\xff\xfe\x00",
                                 bytes(rng.randrange(32, 127) for _ in range(32)), b"SIM-A-HEAD\0junk"))  # fmt: skip
            b[8:40] = serial[:32].ljust(32, b"\0")
        elif r < 0.75:
            b[5] = rng.choice((0, 1, 2, 3, 0xFF))
        else:
            b[4] = rng.choice((0, 2, 0xFF))
        return bytes(b)


def xbus_checksum(b: bytearray) -> None:
    if len(b) >= 4:
        b[-1] = -sum(b[1:-1]) & 0xFF


class Xbus(Protocol):
    """Mutates one Xbus frame; :meth:`Decoders.make_input` joins a stream's frames and cuts them into reads."""

    big = True

    def fields(self, p):
        out: list[Field] = [(1, 1, True), (2, 1, True), (3, 1, True)]
        pos, end = (6 if len(p) > 3 and p[3] == 0xFF else 4), len(p) - 1
        if len(p) > 3 and p[3] == 0xFF:
            out.append((4, 2, True))
        while pos + 3 <= end and len(out) < 24:
            out += [(pos, 2, True), (pos + 2, 1, True)]
            pos += 3 + p[pos + 2]
        return out

    def floats(self, p):
        out = []
        pos, end = 4, len(p) - 1
        while pos + 3 <= end and len(out) < 24:
            size = p[pos + 2]
            out += [(pos + 3 + 4 * k, ">f") for k in range(min(size // 4, 4))]
            pos += 3 + size
        return out

    def fixup(self, rng, b):
        b = bytearray(b)
        if len(b) >= 5 and rng.random() < 0.4:  # length and checksum made right for the data there
            data = b[4:-1] if b[3] != 0xFF else b[6:-1]
            if len(data) <= 254:
                b = bytearray(b[:3]) + bytes([len(data)]) + data + b"\0"
        xbus_checksum(b)
        return bytes(b)

    def special(self, rng, p):
        r = rng.random()
        if r < 0.3:
            return rng.choice((b"\xfa\xff\x36\x00\xcb", b"\xfa\xff\x42\x01\x04\xba", b"\xfa\xff\x3f\x00\xc2",
                               b"\xfa\xff\x36\xff\x00\x00\xcb"))  # fmt: skip
        b = bytearray(p)
        if r < 0.55 and len(b) > 7:  # a record whose size field lies, or an unknown one
            pos = 4 + rng.randrange(0, max(1, len(b) - 8))
            b[pos + 2 if pos + 2 < len(b) - 1 else pos] = rng.choice((0, 1, 3, 4, 0x7F, 0xFF))
        elif r < 0.75 and len(b) > 4:
            b[2] = rng.choice((0x36, 0x32, 0x42, 0x3E, 0x01, 0xC1, 0x00, 0xFF, rng.randrange(256)))
        else:  # extended length
            data = bytes(b[4:-1]) + rng.randbytes(rng.choice((0, 255, 300)))
            b = bytearray(b[:3]) + b"\xff" + struct.pack(">H", len(data)) + data + b"\0"
        xbus_checksum(b)
        return bytes(b)


class MtiCan(Protocol):
    size = 16
    EFF, RTR, ERR = 0x80000000, 0x40000000, 0x20000000
    FIELDS: list[Field] = [(0, 4, False), (0, 2, False), (3, 1, False), (4, 1, False), (5, 1, False), (6, 1, False),
                           (7, 1, False), (8, 2, True), (10, 2, True), (12, 2, True), (14, 2, True), (8, 4, True),
                           (12, 4, True), (8, 8, True)]  # fmt: skip

    def fields(self, p):
        return self.FIELDS

    def special(self, rng, p):
        b = bytearray(p.ljust(16, b"\0")[:16])
        if rng.random() < 0.6:
            cid = rng.choice((0x05, 0x06, 0x11, 0x21, 0x22, 0x32, 0x34, 0x35, 0x41, 0x51, 0x00, 0x7FF,
                              rng.getrandbits(11), rng.getrandbits(29)))  # fmt: skip
            cid |= rng.choice((0, 0, self.EFF, self.RTR, self.ERR, self.EFF | self.RTR, self.ERR | self.RTR))
            struct.pack_into("<I", b, 0, cid)
        else:
            b[4] = rng.choice((0, 1, 4, 7, 8, 9, 15, 64, 255))
            if rng.random() < 0.5:
                struct.pack_into("<I", b, 0, struct.unpack_from("<I", b)[0] | rng.choice((self.EFF, self.RTR, self.ERR)))
        return bytes(b)


class ViveUsb(Protocol):
    size = 52
    FIELDS: list[Field] = [(0, 1, False)] + [f for s in range(3) for f in
                                             [(1 + 17 * s + 2 * k, 2, False) for k in range(6)]
                                             + [(13 + 17 * s, 4, False), (17 + 17 * s, 1, False)]]  # fmt: skip

    def fields(self, p):
        return self.FIELDS

    def special(self, rng, p):
        b = bytearray(p.ljust(52, b"\0")[:52])
        r = rng.random()
        if r < 0.3:
            b[0] = rng.choice((0x20, 0x21, 0x23, 0x24, 0x25, 0x26, 0x27, 0x28, 0x00, 0xFF))
        elif r < 0.6:  # a slot repeated into another, or time running back
            s, t = rng.randrange(3), rng.randrange(3)
            b[1 + 17 * t:18 + 17 * t] = b[1 + 17 * s:18 + 17 * s]
        else:
            s = rng.randrange(3)
            set_int(b, 13 + 17 * s, 4, rng.choice((0, 1, 2**31, 2**32 - 1, rng.getrandbits(32))), False)
        return bytes(b)


PROTOCOLS: dict[str, Protocol] = {"mvn": Mvn(), "vive": Vive(), "xbus": Xbus(), "mti-can": MtiCan(),
                                  "vive-usb": ViveUsb()}  # fmt: skip


# =============================================================================================== corpus
def corpus_digest(folder: Path = CORPUS) -> dict[str, str]:
    """SHA-256 (first 16 hex digits) of every corpus file, by path relative to the corpus."""
    out = {}
    for p in sorted(folder.rglob("*")):
        if p.is_file():
            out[p.relative_to(folder).as_posix()] = hashlib.sha256(p.read_bytes()).hexdigest()[:16]
    return out


def build_corpus(folder: Path = CORPUS, progress: Callable[[str], None] = print) -> None:
    """Make the corpus in ``folder`` (see the module docstring); slow (the body model, a scene), done once."""
    import numpy as np

    tmp = folder.with_name(folder.name + ".part")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    progress("fuzz corpus: simulating a handshake (the scene, then every device)...")
    from dualhuman_builder.sim.scenes import SceneParams, make_scene
    from dualhuman_builder.sim.studio import simulate_studio

    studio = simulate_studio(make_scene(SceneParams(type="handshake", seed=1, fps=15.0, tempo=2.0)).sequence, seed=1)
    packets = studio_packets(studio)
    arrays = {}
    for name, pkts in packets.items():
        arrays[f"{name}.t"] = np.array([t for t, _ in pkts], np.int64)
        arrays[f"{name}.n"] = np.array([len(d) for _, d in pkts], np.int64)
        arrays[f"{name}.data"] = np.frombuffer(b"".join(d for _, d in pkts), np.uint8)
    np.savez(tmp / "packets.npz", **arrays)
    progress("fuzz corpus: a small take, MVNX and BVH files, an export, annotation files...")
    write_small_take(tmp / "take.mcap", packets)
    write_small_skeleton_files(tmp, studio.suits[0])
    write_small_export(tmp / "export")
    write_annotation_files(tmp)
    shutil.rmtree(folder, ignore_errors=True)
    tmp.rename(folder)


def studio_packets(studio) -> dict[str, list[tuple[int, bytes]]]:
    """Every device's packets of a simulated studio, as the loopback studio sends them: ``{decoder name:
    [(host time ns, bytes)]}``. MVN starts with meta and scale messages; one suit splits its poses over three
    datagrams; the VIVE USB reports carry the Xbus IMU's readings on a tick clock that wraps."""
    from dualhuman_builder.body.mapping import MVN_SEGMENTS
    from dualhuman_builder.capture.wire.mti_can import pack_can_frame
    from dualhuman_builder.capture.wire.mvn import ScalePoint, encode_meta, encode_scale
    from dualhuman_builder.capture.wire.vive_hid import HidImuSample, counts_from_si, encode_imu_report
    from dualhuman_builder.capture.wire.xbus import MID, SimulatedMti, encode_message
    from dualhuman_builder.sim.devices import can_packets, merge, mvn_packets, tracker_packets

    origins = {s: (0.0, 0.05 * i, 0.0) for i, s in enumerate(MVN_SEGMENTS)}
    points = [ScalePoint(1, 0, "pHipOrigin", 0, (0.0, 0.0, 0.0)), ScalePoint(7, 1, "pTopOfHead", 1, (0.0, 0.2, 0.0))]
    prologue = [*encode_meta(0, name="sim-a", xmid="00112233", color="FF8000"), *encode_meta(1, name="sim-b"),
                *encode_scale(0, origins, points)]  # fmt: skip
    suits = [mvn_packets(s, clock="host", prologue=prologue if i == 0 else (), max_datagram=1500 if i == 0 else 400)
             for i, s in enumerate(studio.suits)]  # fmt: skip
    out: dict[str, list[tuple[int, bytes]]] = {}
    out["mvn"] = [(p.time_ns, bytes(p.data)) for p in merge(*suits)]
    out["vive"] = [(p.time_ns, p.data) for p in merge(*(tracker_packets(tr, clock="host") for tr in studio.trackers))]
    imu_x, imu_c = studio.imus["mti-xbus"], studio.imus["mti-can"]
    mti = SimulatedMti()
    xs = [(int(s.host_time_ns), mti.mtdata2(s)) for s in imu_x]
    t0 = xs[0][0]
    others = [encode_message(MID.WAKE_UP_ACK), encode_message(MID.ERROR, b"\x04"),
              encode_message(MID.DEVICE_ID, b"\x03\x60\x12\x34")]  # fmt: skip
    out["xbus"] = [(t0 - 1000 * (3 - k), m) for k, m in enumerate(others)] + xs
    out["mti-can"] = [(p.time_ns, pack_can_frame(p.data)) for p in can_packets(imu_c, clock="host")]
    slots = []
    tick0 = 2**32 - 48_000_000 // 2  # the u32 tick counter wraps half a second in
    for k, s in enumerate(imu_x):
        acc, gyro = counts_from_si(s.acceleration, s.rate_of_turn)
        ticks = (tick0 + (int(s.device_time_ns) - int(imu_x.device_time_ns[0])) * 6 // 125) % 2**32
        slots.append((int(s.host_time_ns), HidImuSample(acc, gyro, ticks, k & 0xFF)))
    out["vive-usb"] = [(slots[k][0], encode_imu_report([slots[max(k - 2, 0)][1], slots[max(k - 1, 0)][1], slots[k][1]]))
                       for k in range(len(slots))]  # fmt: skip
    return out


def serial_reads(frames: list[tuple[int, bytes]], rng: random.Random) -> list[tuple[int, bytes]]:
    """Xbus frames as a serial port delivers them: the byte stream cut into reads of 1 to 300 bytes, at times of
    the frames they end in."""
    stream = b"".join(d for _, d in frames)
    ends, pos = [], 0
    for t, d in frames:
        pos += len(d)
        ends.append((pos, t))
    out, i, k = [], 0, 0
    while i < len(stream):
        j = min(len(stream), i + rng.choice((1, 7, 40, 80, 120, 300)))
        while k < len(ends) - 1 and ends[k][0] < j:
            k += 1
        out.append((ends[k][1], stream[i:j]))
        i = j
    return out


def write_small_take(path: Path, packets: dict[str, list[tuple[int, bytes]]]) -> None:
    """A take of the first tens of milliseconds of the simulated studio (of the trackers, six datagrams), written as
    the recorder writes one (the take writer, the real decoders, events and a status, 4 KiB chunks), with the studio
    rig's text and bindings."""
    from dualhuman_builder.capture.log.writer import TakeWriter
    from dualhuman_builder.capture.recorder import rig_bindings
    from dualhuman_builder.capture.sources import RawPacket, make_decoder
    from dualhuman_builder.resources import RIGS_DIR
    from dualhuman_builder.rig import load_rig

    rig = load_rig(RIGS_DIR / "sim.toml")
    sources = [("suits", "mvn+udp://127.0.0.1:9763", "mvn", "mvn"), ("trackers", "vive+udp://127.0.0.1:8051", "vive", "vive"),
               ("floor-imu", "mti+can://virtual/dualhuman-sim?device=mti-can", "mti-can", "mti-can"),
               ("prop-imu", "xbus://loop?device=mti-xbus", "xbus", "xbus")]  # fmt: skip
    window = {"mvn": 12_000_000, "mti-can": 30_000_000, "xbus": 20_000_000}  # ns from each source's first packet
    merged = []
    for k, (_, _, _, corpus) in enumerate(sources):
        t0 = packets[corpus][0][0]
        pkts = [p for p in packets[corpus] if p[0] - t0 < window[corpus]] if corpus in window else packets[corpus][:6]
        if corpus == "xbus":
            pkts = serial_reads(pkts, random.Random(0))
        merged += [(t, k, d) for t, d in pkts]
    merged.sort(key=lambda x: (x[0], x[1]))
    decoders = [make_decoder(url) for _, url, _, _ in sources]
    w = TakeWriter(path, take="FUZZ", sources=[(n, u, k) for n, u, k, _ in sources], bindings=rig_bindings(rig.actors),
                   rig_text=rig.text, chunk_size=4096, foxglove_hz=30.0)  # fmt: skip
    for t, k, d in merged:
        packet = RawPacket(t, d)
        w.add_raw(k, packet)
        for s in decoders[k].feed(packet):
            w.add_sample(k, s)
        for ev in decoders[k].pop_events():
            w.add_event(sources[k][0], ev)
    for k, dec in enumerate(decoders):
        for s in dec.finish():
            w.add_sample(k, s)
    w.add_status(merged[-1][0], {n: dict(d.counters) for (n, _, _, _), d in zip(sources, decoders)})
    w.close(stats={n: dict(d.counters) for (n, _, _, _), d in zip(sources, decoders)})


def write_small_skeleton_files(folder: Path, suit) -> None:
    """``small.mvnx`` (2 frames, two calibration poses, the per-frame arrays of a real export) and ``small.bvh``
    (6 frames) of a simulated suit (a :class:`~dualhuman_builder.sim.suit.SuitStream`)."""
    from dualhuman_builder.sim.files import ERGONOMIC_JOINTS, identity_pose, mvnx_arrays_from_suit, write_bvh, write_mvnx

    track = suit.to_track()
    short = _first_frames(track, 2)
    arrays = {k: v[:2] for k, v in mvnx_arrays_from_suit(suit).items()}
    write_mvnx(folder / "small.mvnx", short, arrays=arrays, ergonomic_joints=ERGONOMIC_JOINTS,
               calibration={"identity": identity_pose(short), "tpose": (short.orientations[0], short.positions[0])},
               start_epoch_ms=1_700_000_000_000, subject={"label": "alice"})  # fmt: skip
    write_bvh(folder / "small.bvh", _first_frames(track, 6))


def _first_frames(track, n: int):
    from dualhuman_builder.tracks import SkeletonTrack

    return SkeletonTrack(track.segment_names, track.orientations[:n], track.positions[:n], track.device_time_ns[:n],
                         track.host_time_ns[:n], actor=track.actor, fps=track.fps)  # fmt: skip


def write_small_export(folder: Path) -> None:
    """A dataset export of one 6-frame sequence of two anny bodies (no contacts, no renders)."""
    import numpy as np

    from dualhuman_builder.body.model import get_body_model
    from dualhuman_builder.export.items import ExportItem
    from dualhuman_builder.export.writer import export_dataset
    from dualhuman_builder.tracks import BodyTrack, InteractionSequence

    model = get_body_model()

    def track(seed: int, x: float, actor: str) -> BodyTrack:
        rng = np.random.default_rng(seed)
        pose = np.cumsum(rng.normal(0.0, 0.01, (6, model.num_bones, 3)), axis=0)
        transl = np.stack([np.full(6, x), np.full(6, 0.95), np.linspace(0.0, 0.06, 6)], axis=1)
        return BodyTrack.from_model(model, pose, transl, rng.uniform(0.3, 0.7, len(model.shape_names)), 20.0, actor=actor)

    items = [ExportItem(f"s{k}", InteractionSequence((track(k, 0.0, "alice"), track(k + 10, 0.9, "bob")), take=f"take{k}",
                                                     labels=("push",), text=("The person on the left pushes the other.",)),
                        subjects=("alice", "bob"), roles=("actor", "reactor")) for k in range(1)]  # fmt: skip
    export_dataset(items, folder, seed=3)


ANNOTATION_ROWS = [
    {"take": "T1", "sequence": "S1", "labels": "hug", "actor": "alice", "reactor": "bob", "symmetric": "",
     "annotator": "ann", "annotated_at": "2026-01-01T00:00:00Z", "texts": ["Two friends embrace \u2014 caf\u00e9."]},
    {"take": "T1", "sequence": "", "labels": "push;handshake", "actor": "bob", "reactor": "alice", "symmetric": "false",
     "annotator": "ann", "annotated_at": "", "texts": ["One pushes.", "Then they shake hands."]},
    {"take": "T2", "sequence": "", "labels": "", "actor": "", "reactor": "", "symmetric": "", "annotator": "",
     "annotated_at": "", "texts": []},
    {"take": "T2", "sequence": "", "labels": "high_five", "actor": "", "reactor": "", "symmetric": "yes",
     "annotator": "bo", "annotated_at": "2026-02-03T04:05:06+01:00", "texts": ["A high five."]},
]  # fmt: skip


def write_annotation_files(folder: Path) -> None:
    """``annotations.csv`` and ``annotations.jsonl``: the same rows (one blank) for the workspace of
    :func:`annotation_workspace`."""
    import csv

    from dualhuman_builder.export.annotate import FIELDS

    buf = io.StringIO(newline="")
    w = csv.writer(buf, lineterminator="\n")
    w.writerow([*FIELDS, "text_1", "text_2"])
    for r in ANNOTATION_ROWS:
        w.writerow([r[k] for k in FIELDS] + (r["texts"] + ["", ""])[:2])
    (folder / "annotations.csv").write_text(buf.getvalue(), encoding="utf-8")
    lines = []
    for r in ANNOTATION_ROWS:
        rec = {k: r[k] for k in FIELDS if r[k]}
        rec["labels"] = r["labels"].split(";") if r["labels"] else []
        rec["texts"] = r["texts"]
        lines.append(json.dumps(rec, ensure_ascii=False))
    (folder / "annotations.jsonl").write_text("\n".join(lines) + "\n", encoding="utf-8")


def annotation_workspace(root: Path):
    """A workspace with actors alice, bob, carol; takes T1 (alice, bob) with sequence S1, and T2 (bob, carol)."""
    from dualhuman_builder.workspace import Workspace

    w = Workspace.init(root)
    for name in ("alice", "bob", "carol"):
        w.add_actor(name, 1.7)
    w.add_take("T1", actors=["alice", "bob"])
    w.add_take("T2", actors=["bob", "carol"])
    w.add_sequence("T1", "S1", 0, 40, labels=("hug",))
    return w


def load_packets(folder: Path = CORPUS) -> dict[str, list[tuple[int, bytes]]]:
    import numpy as np

    with np.load(folder / "packets.npz", allow_pickle=False) as z:
        names = sorted({k.rsplit(".", 1)[0] for k in z.files})
        out = {}
        for name in names:
            t, n, data = z[f"{name}.t"].tolist(), z[f"{name}.n"], z[f"{name}.data"].tobytes()
            ends = n.cumsum().tolist()
            out[name] = [(t[i], data[(ends[i - 1] if i else 0):ends[i]]) for i in range(len(t))]
    return out


# =============================================================================================== targets
def where_raised(tb) -> str:
    """``path:line`` of the innermost frame in the package (else the innermost frame) of a traceback."""
    frames = traceback.extract_tb(tb)
    pkg = [f for f in frames if "dualhuman_builder" in f.filename]
    f = (pkg or frames or [None])[-1]
    if f is None:
        return "?"
    name = f.filename
    if "dualhuman_builder" in name:
        name = name[name.rindex("dualhuman_builder") + len("dualhuman_builder/"):]
    else:
        name = Path(name).name
    return f"{name}:{f.lineno}"


class Escape:
    """One exception out of one operation: ``op``, the exception's ``type``, ``where`` it was raised and a short
    ``message`` (``exc`` None: the fields given, as a decoder's guard reports an exception it caught)."""

    def __init__(self, op: str, exc: BaseException | None, *, exc_type: str = "", where: str = "", message: str = ""):
        self.op = op
        if exc is None:
            self.type, self.where, self.message, self.trace = exc_type, where, message, ""
            return
        self.type = "hang" if isinstance(exc, InputTimeout) else type(exc).__name__
        self.where = where_raised(exc.__traceback__)
        self.message = " ".join(str(exc).split())[:240]
        self.trace = "".join(traceback.format_exception(exc)[-6:])[-3000:]

    @property
    def key(self) -> str:
        return f"{self.op}: {self.type} at {self.where}"


class Target:
    """One fuzzed thing. ``make_input(rng, index)`` builds input ``index``; ``run(index, input)`` returns the
    escapes; ``save(input, escape, stem)`` writes a reproducer and returns its paths."""

    name = ""
    kind = ""
    timeout = INPUT_TIMEOUT_S

    def guarded(self, op: str, fn: Callable, *args, clear: tuple[type, ...] = ()) -> Escape | None:
        """``fn(*args)`` under the input time limit; an exception that is not one of ``clear`` is an escape."""
        signal.setitimer(signal.ITIMER_REAL, self.timeout)
        try:
            fn(*args)
        except KeyboardInterrupt:
            raise
        except clear:
            return None
        except BaseException as e:  # noqa: BLE001 - what escapes is the finding
            return Escape(op, e)
        finally:
            signal.setitimer(signal.ITIMER_REAL, 0)
        return None

    def warm(self) -> None:
        """Run the pristine input once (imports done, caches filled) before the address space is capped."""

    def close(self) -> None:
        pass


class DecoderTarget(Target):
    kind = "decoder"
    LENGTHS = (1, 1, 2, 3, 4, 6, 8, 12, 16, 24, 32, 48, 64, 128)

    def __init__(self, name: str, packets: dict[str, list[tuple[int, bytes]]]):
        self.name, self.url, self.proto = name, DECODERS[name], PROTOCOLS[name]
        self.corpus = packets[name]
        self.pool = [d for _, d in self.corpus[::7]] + [d for n, ps in packets.items() if n != name for _, d in ps[::97]]
        self.foreign = [d for n, ps in packets.items() if n != name for _, d in ps[::13]]
        self.decoder = None
        self.session: list[list[tuple[int, bytes]]] = []
        self.stop = 0
        self.caught: list[Escape] = []
        self.caught_count = 0

    def make_input(self, rng: random.Random, index: int) -> list[tuple[int, bytes]]:
        c = self.corpus
        if rng.random() < 0.08:  # random bytes, sometimes behind a real header
            t0 = c[rng.randrange(len(c))][0]
            out = []
            for j in range(rng.choice((1, 1, 2, 4, 16, 64))):
                head = c[rng.randrange(len(c))][1][:rng.choice((0, 0, 2, 4, 6, 24))]
                out.append((t0 + 1000 * j, head + rng.randbytes(rng.choice((0, 1, 2, 8, 16, 24, 52, 128, 700, 1500, 4000)))))
            return out
        start = rng.randrange(len(c))
        pkts = [list(p) for p in c[start:start + rng.choice(self.LENGTHS)]]
        for _ in range(rng.choice((0, 1, 1, 1, 2, 3, 5))):
            j = rng.randrange(len(pkts))
            pkts[j][1] = self.proto.mutate(rng, pkts[j][1], self.pool)
        for _ in range(rng.choice((0, 0, 0, 1, 1, 2))):
            pkts = self.stream_op(rng, pkts)
        out = [(int(t), bytes(d)) for t, d in pkts]
        if self.name == "xbus":
            out = serial_reads(out, rng) if rng.random() < 0.7 else out
        return out

    def stream_op(self, rng: random.Random, pkts: list[list]) -> list[list]:
        op = rng.randrange(10)
        n = len(pkts)
        if op == 0 and n > 1:
            del pkts[rng.randrange(n)]
        elif op == 1:
            j = rng.randrange(n)
            pkts[j + 1:j + 1] = [list(pkts[j]) for _ in range(rng.choice((1, 2, 5)))]
        elif op == 2 and n > 1:
            i, j = rng.randrange(n), rng.randrange(n)
            pkts[i], pkts[j] = pkts[j], pkts[i]
        elif op == 3:
            pkts.reverse()
        elif op == 4:
            rng.shuffle(pkts)
        elif op == 5:  # a flood of one packet
            j = rng.randrange(n)
            pkts[j + 1:j + 1] = [[pkts[j][0] + k, pkts[j][1]] for k in range(rng.choice((30, 100, 300, 1000)))]
        elif op == 6:
            j = rng.randrange(n + 1)
            pkts.insert(j, [pkts[min(j, n - 1)][0], rng.choice(self.foreign)])
        elif op == 7:
            t = pkts[0][0]
            for p in pkts:
                p[0] = t
        elif op == 8:
            j = rng.randrange(n)
            shift = rng.choice((-10**9, -10**12, 10**12, 10**15, -1))
            for p in pkts[j:]:
                p[0] = p[0] + shift
            if rng.random() < 0.3:
                pkts[j][0] = rng.choice((0, 1, 2**63 - 1, 2**64 - 1))
            for p in pkts:
                p[0] = min(max(p[0], 0), 2**64 - 1)
        else:
            pkts = pkts * rng.choice((2, 3, 5))
        return pkts[:4000]

    def warm(self) -> None:
        self._replay(self.corpus[:64])

    def new_decoder(self):
        from dualhuman_builder.capture.sources import make_decoder

        return make_decoder(self.url)

    GUARD_EVENT = re.compile(r"^\w+\.(\w+) raised (\w+)(?: at (\S+:\d+))?: (.*?); counted decoder_errors")

    def _feed_all(self, dec, packets: list[tuple[int, bytes]]) -> None:
        """Feed ``packets``, ask for the status at the last one's time (as the recorder does), drain the events."""
        from dualhuman_builder.capture.sources import RawPacket

        for t, d in packets:
            dec.feed(RawPacket(t, d))
        if packets:
            dec.status(packets[-1][0])
        self._drain(dec)

    def _finish(self, dec) -> None:
        dec.finish()
        self._drain(dec)

    def _drain(self, dec) -> None:
        """The exceptions the decoders' guard caught (its ``decoder-error`` events) into :attr:`caught`."""
        for ev in dec.pop_events():
            if ev.kind == "decoder-error":
                m = self.GUARD_EVENT.match(ev.message)
                if m:
                    self.caught.append(Escape(m[1], None, exc_type=m[2], where=m[3] or "?", message=m[4][:240]))

    def run(self, index: int, packets: list[tuple[int, bytes]]) -> list[Escape]:
        """Feed one stream; the session's decoder ends with ``finish()``. Exceptions out of ``feed``, ``status``
        or ``finish`` are returned; those the decoders' guard caught and counted are left in :attr:`caught`
        (``caught_count``: how many, from the ``decoder_errors`` counter)."""
        if self.decoder is None:
            self.decoder, self.session = self.new_decoder(), []
        self.session.append(packets)
        self.caught, out = [], []
        before = self.decoder.counters.get("decoder_errors", 0)
        e = self.guarded("feed", self._feed_all, self.decoder, packets)
        if e is not None:
            out.append(e)
        elif (index + 1) % SESSION == 0 or index + 1 >= self.stop:
            e = self.guarded("finish", self._finish, self.decoder)
            if e is not None:
                out.append(e)
        self.caught_count = self.decoder.counters.get("decoder_errors", 0) - before
        if out or (index + 1) % SESSION == 0 or index + 1 >= self.stop:
            self.decoder = None  # a decoder that raised is dead, as its process would be
        return out

    def _replay(self, packets: list[tuple[int, bytes]]) -> None:
        self.caught = []
        dec = self.new_decoder()
        self._feed_all(dec, packets)
        self._finish(dec)

    def save(self, packets, esc: Escape, stem: Path) -> list[Path]:
        """The failing stream alone when it fails the same way on a fresh decoder, else the session's streams
        up to it."""
        caught = esc.trace == ""
        alone = self.guarded(esc.op, self._replay, packets)
        if caught:
            alone = next((c for c in self.caught if c.key == esc.key), None)
        fresh = alone is not None and alone.type == esc.type
        stream = packets if fresh else [p for s in self.session for p in s]
        if sum(len(d) for _, d in stream) > 8 << 20:
            stream, fresh = packets, False
        doc = {"target": self.name, "url": self.url, "fresh_decoder": fresh,
               "packets": [[t, d.hex()] for t, d in stream]}  # fmt: skip
        path = stem.with_suffix(".json")
        return [path], doc


class FileTarget(Target):
    """A file reader: each input is the bytes of one file, written to a temporary file and read by :meth:`ops`."""

    kind = "reader"
    suffix = ""

    def __init__(self, tmp: Path):
        self.tmp = tmp
        self.path = tmp / f"input{self.suffix}"

    def ops(self, path: Path) -> list[tuple[str, Callable, tuple]]:
        raise NotImplementedError

    def run(self, index: int, data: bytes) -> list[Escape]:
        from dualhuman_builder.errors import DualhumanError

        self.path.write_bytes(data)
        out = []
        for op, fn, args in self.ops(self.path):
            e = self.guarded(op, fn, *args, clear=(DualhumanError,))
            if e is not None:
                out.append(e)
        return out

    def warm(self) -> None:
        self.run(0, self.pristine)

    def save(self, data: bytes, esc: Escape, stem: Path):
        path = stem.with_suffix(self.suffix)
        path.write_bytes(data)
        return [path], {"target": self.name, "file": path.name}

    def replay(self, doc: dict, folder: Path) -> None:
        for op, fn, args in self.ops(folder / doc["file"]):
            if op == doc["op"]:
                fn(*args)


class TextMutator:
    """Mutations of a text file along its tokens: numbers and attribute values set to extremes, lines dropped,
    repeated, swapped, ``tokens`` of the format inserted, huge runs, truncation; or byte-level."""

    NUM = re.compile(rb"-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
    ATTR = re.compile(rb'="([^"]*)"')

    def __init__(self, data: bytes, tokens: list[bytes], huge: list[bytes] = ()):
        self.data, self.tokens, self.huge = data, tokens, list(huge)
        self.nums = [m.span() for m in self.NUM.finditer(data)]
        self.attrs = [m.span(1) for m in self.ATTR.finditer(data)]

    def mutate(self, rng: random.Random, data: bytes | None = None) -> bytes:
        base = self.data if data is None else data
        r = rng.random()
        if r < 0.3 and data is None and self.nums:
            spans = sorted(rng.sample(self.nums, min(len(self.nums), rng.choice((1, 1, 2, 3, 8)))), reverse=True)
            b = base
            for i, j in spans:
                b = b[:i] + rng.choice(NUMBERS) + b[j:]
        elif r < 0.42 and data is None and self.attrs:
            i, j = rng.choice(self.attrs)
            b = base[:i] + rng.choice((*NUMBERS, b"", b"normal", b"identity", b"&lt;", b"A" * 70000, b"\x01")) + base[j:]
        elif r < 0.6:
            lines = base.split(b"\n")
            k = rng.randrange(len(lines))
            op = rng.randrange(4)
            if op == 0:
                del lines[k:k + rng.choice((1, 1, 2, 5, 20))]
            elif op == 1:
                lines[k:k] = lines[k:k + rng.choice((1, 2, 5))] * rng.choice((1, 2, 10, 100))
            elif op == 2:
                m = rng.randrange(len(lines))
                lines[k], lines[m] = lines[m], lines[k]
            else:
                lines.insert(k, lines[rng.randrange(len(lines))])
            b = b"\n".join(lines)
        elif r < 0.72:
            i = rng.randrange(len(base) + 1)
            b = base[:i] + rng.choice(self.tokens) + base[i:]
        elif r < 0.8:
            b = base[:rng.randrange(len(base) + 1)]
        elif r < 0.85 and self.huge:
            i = rng.randrange(len(base) + 1)
            b = base[:i] + rng.choice(self.huge) + base[i:]
        else:
            b = mutate_bytes(rng, base)
        if data is None and rng.random() < 0.3:
            b = self.mutate(rng, b)
        return b


class TakeTarget(FileTarget):
    """Mutated takes: bytes anywhere, a record's length or opcode, records deleted, repeated or swapped, a chunk
    rebuilt around mutated records (valid CRC or none, LZ4, zstd or none), cuts as a crash leaves, the footer."""

    name, suffix = "take", ".mcap"

    def __init__(self, tmp: Path, corpus: Path):
        super().__init__(tmp)
        self.pristine = (corpus / "take.mcap").read_bytes()
        self.out = tmp / "repaired.mcap"
        self.records = self._records(self.pristine, 8, len(self.pristine) - 8)
        self.chunks = [r for r in self.records if r[1] == 0x06]
        self.fields: list[Field] = [f for off, op, n in self.records for f in ((off, 1, False), (off + 1, 8, False))]
        self.fields += [(len(self.pristine) - 28, 8, False), (len(self.pristine) - 20, 8, False),
                        (len(self.pristine) - 12, 4, False)]  # fmt: skip
        for off, _, _ in self.chunks:
            self.fields += [(off + 9 + k, 8, False) for k in (0, 8, 16)] + [(off + 33, 4, False), (off + 37, 4, False)]

    @staticmethod
    def _records(data: bytes, start: int, end: int) -> list[tuple[int, int, int]]:
        """``(offset, opcode, body length)`` of the records between ``start`` and ``end``."""
        out, pos = [], start
        while pos + 9 <= end:
            op, n = struct.unpack_from("<BQ", data, pos)
            out.append((pos, op, n))
            pos += 9 + n
        return out

    def _chunk(self, rng: random.Random, off: int, n: int) -> bytes:
        """The chunk record at ``off`` rebuilt with mutated contents."""
        import lz4.frame

        body = self.pristine[off + 9:off + 9 + n]
        start, end, usize, crc = struct.unpack_from("<QQQI", body, 0)
        clen = struct.unpack_from("<I", body, 28)[0]
        comp = body[32:32 + clen]
        rlen = struct.unpack_from("<Q", body, 32 + clen)[0]
        data = body[40 + clen:40 + clen + rlen]
        inner = lz4.frame.decompress(data) if comp == b"lz4" else data
        recs = self._records(inner, 0, len(inner))
        fields: list[Field] = []
        for ioff, op, _ in recs[:64]:
            fields += [(ioff, 1, False), (ioff + 1, 8, False), (ioff + 9, 2, False)]
            if op == 0x05:  # message: channel, sequence, log and publish time
                fields += [(ioff + 11, 4, False), (ioff + 15, 8, False), (ioff + 23, 8, False)]
            elif op in (0x03, 0x04):  # schema / channel: ids and the first string's length
                fields += [(ioff + 11, 2, False), (ioff + 11, 4, False), (ioff + 13, 4, False)]
        if rng.random() < 0.3 and len(recs) > 1:  # records dropped, repeated, swapped
            parts = [inner[o:o + 9 + m] for o, _, m in recs]
            k = rng.randrange(len(parts))
            op = rng.randrange(3)
            if op == 0:
                del parts[k]
            elif op == 1:
                parts.insert(k, parts[k] * rng.choice((1, 2, 50)))
            else:
                m = rng.randrange(len(parts))
                parts[k], parts[m] = parts[m], parts[k]
            new = b"".join(parts)
        else:
            new = mutate_bytes(rng, inner, fields=fields, pool=[inner[o:o + 9 + m] for o, _, m in recs[:32]])
        c = rng.random()
        if c < 0.6:
            comp, data = b"lz4", lz4.frame.compress(new)
        elif c < 0.8:
            comp, data = b"", new
        elif c < 0.9:
            import zstandard

            comp, data = b"zstd", zstandard.ZstdCompressor().compress(new)
        else:
            comp, data = rng.choice((b"gzip", b"LZ4", b"")), new
        usize = len(new) if rng.random() < 0.9 else rng.choice((0, len(new) + 1, 2**31, 2**63, 2**64 - 1))
        crc = zlib.crc32(new) if rng.random() < 0.7 else rng.choice((0, 0, 1))
        body = struct.pack("<QQQI", start, end, usize, crc) + struct.pack("<I", len(comp)) + comp
        body += struct.pack("<Q", len(data)) + data
        return struct.pack("<BQ", 0x06, len(body)) + body

    def _mutated(self, rng: random.Random) -> bytes:
        p = self.pristine
        r = rng.random()
        if r < 0.3:
            return mutate_bytes(rng, p, fields=self.fields)
        if r < 0.6 and self.chunks:
            off, _, n = rng.choice(self.chunks)
            b = p[:off] + self._chunk(rng, off, n) + p[off + 9 + n:]
            return b if rng.random() < 0.7 else b[:rng.randrange(len(b) + 1)]
        if r < 0.75:  # whole records
            recs = self.records
            parts = [p[:8]] + [p[o:o + 9 + n] for o, _, n in recs] + [p[recs[-1][0] + 9 + recs[-1][2]:]]
            k = rng.randrange(1, len(parts) - 1)
            op = rng.randrange(4)
            if op == 0:
                del parts[k]
            elif op == 1:
                parts.insert(k, parts[k] * rng.choice((1, 2, 20)))
            elif op == 2:
                m = rng.randrange(1, len(parts) - 1)
                parts[k], parts[m] = parts[m], parts[k]
            else:
                parts[k] = mutate_bytes(rng, parts[k], fields=[(0, 1, False), (1, 8, False)])
            return b"".join(parts)
        if r < 0.9:  # cut off, as a crash leaves a take, maybe with garbage after
            b = p[:rng.randrange(len(p) + 1)]
            return b + (rng.randbytes(rng.choice((1, 9, 100))) if rng.random() < 0.3 else b"")
        b = bytearray(p)  # the summary and footer
        off = len(p) - 28
        set_int(b, off + rng.choice((0, 8)), 8, rng.choice(INTS[8] + (rng.randrange(len(p)),)), False)
        return bytes(b)

    def _messages(self, path: Path) -> None:
        from dualhuman_builder.capture.log.reader import TakeReader

        r = TakeReader(path)
        for _ in r.raw_packets():
            pass
        r.take_meta()

    def _samples(self, path: Path) -> None:
        from dualhuman_builder.capture.log.reader import TakeReader

        for _ in TakeReader(path).samples():
            pass

    def _repair(self, path: Path) -> None:
        from dualhuman_builder.capture.log.reader import check_take
        from dualhuman_builder.capture.log.repair import repair_take
        from dualhuman_builder.errors import FormatError

        self.out.unlink(missing_ok=True)
        try:
            repair_take(path, self.out)
        except FormatError as e:
            if "nothing to repair" in str(e):
                return
            raise
        check_take(self.out)

    #: The operations besides ``messages`` (which reads every input), with the share of inputs each reads: one of
    #: them per input keeps 100,000 inputs within minutes.
    SOME = (("read_columns", 0.35), ("check_take", 0.25), ("samples", 0.15), ("dump_jsonl", 0.15), ("repair_take", 0.1))

    def make_input(self, rng: random.Random, index: int) -> bytes:
        r, acc = rng.random(), 0.0
        for op, share in self.SOME:
            acc += share
            if r < acc:
                break
        self.op = op
        return self._mutated(rng)

    def ops(self, path):
        from dualhuman_builder.capture.log.reader import check_take, dump_jsonl, read_columns

        every = [("messages", self._messages, (path,))]
        some = {"read_columns": (read_columns, (path,)), "check_take": (check_take, (path,)), "samples": (self._samples, (path,)),
                "dump_jsonl": (dump_jsonl, (path, io.StringIO())), "repair_take": (self._repair, (path,))}  # fmt: skip
        chosen = [getattr(self, "op", None)] if getattr(self, "op", None) else list(some)
        return every + [(op, *some[op]) for op in chosen]

    def warm(self) -> None:
        self.op = None
        self.run(0, self.pristine)

    def save(self, data: bytes, esc: Escape, stem: Path):
        paths, doc = super().save(data, esc, stem)
        return paths, dict(doc, ops=[op for op, _, _ in self.ops(self.path)])


MVNX_TOKENS = [b'<frame time="0" index="9" tc="00:00:00:00" ms="1" type="normal">', b"</frame>", b"<frames>", b"</frames>",
               b'<segment label="Prop1" id="24">', b"</segment>", b"<orientation>1 0 0 0</orientation>",
               b"<position>0 0 0</position>", b'segmentCount="999999999"', b'sensorCount="2000000000"',
               b'jointCount="-5"', b'frameRate="0"', b'<frame type="tpose">', b"<![CDATA[x]]>", b"&amp;", b"&x;",
               b"<!-- -->", b'<?xml version="1.0" encoding="UTF-16"?>', b"\x00", b"\xff\xfe", b"<a><b><c>",
               b'xmlns="http://example.com/other"', b"<points></points>", b"</mvnx>"]  # fmt: skip
ENTITY_BOMB = (b'<!DOCTYPE mvnx [<!ENTITY a "aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa">'
               + b"".join(b'<!ENTITY %s "%s">' % (bytes([98 + k]), (b"&%s;" % bytes([97 + k])) * 10) for k in range(8))
               + b"]>")  # fmt: skip


class MvnxTarget(FileTarget):
    name, suffix = "mvnx", ".mvnx"

    def __init__(self, tmp: Path, corpus: Path):
        super().__init__(tmp)
        self.pristine = (corpus / "small.mvnx").read_bytes()
        huge = [b"<a>" * 100_000, b"0 " * 200_000, ENTITY_BOMB, b'<!DOCTYPE x [<!ENTITY e SYSTEM "file:///etc/passwd">]>']
        self.text = TextMutator(self.pristine, MVNX_TOKENS, huge)

    def make_input(self, rng: random.Random, index: int) -> bytes:
        b = self.text.mutate(rng)
        if rng.random() < 0.03:  # a document type before the root
            i = self.pristine.find(b"<mvnx")
            b = b[:i] + rng.choice((ENTITY_BOMB, b'<!DOCTYPE mvnx SYSTEM "http://127.0.0.1:9/x.dtd">')) + b[i:]
        return b

    def _read(self, path: Path) -> None:
        from dualhuman_builder.capture import importers
        from dualhuman_builder.capture.importers.mvnx import read_mvnx

        mf = read_mvnx(path)
        extras = getattr(importers, "_mvnx_extras", None)
        if extras is not None:
            extras(mf)
        mf.track.save(self.tmp / "skeleton.npz")

    def ops(self, path):
        return [("read_mvnx", self._read, (path,))]


BVH_TOKENS = [b"ROOT", b"JOINT", b"End Site", b"{", b"}", b"OFFSET 0 0 0", b"OFFSET", b"CHANNELS 6", b"CHANNELS 3",
              b"CHANNELS 999999999", b"CHANNELS -1", b"Xposition", b"Zrotation", b"Wrotation", b"MOTION", b"HIERARCHY",
              b"Frames: 999999999", b"Frames: -1", b"Frames: 0", b"Frame Time: 0", b"Frame Time: -0.1",
              b"Frame Time: nan", b"\t", b"\r", b"\x00", b"\xff"]  # fmt: skip


class BvhTarget(FileTarget):
    name, suffix = "bvh", ".bvh"

    def __init__(self, tmp: Path, corpus: Path):
        super().__init__(tmp)
        self.pristine = (corpus / "small.bvh").read_bytes()
        huge = [b"JOINT j\n{\nOFFSET 0 0 0\nCHANNELS 3 Zrotation Xrotation Yrotation\n" * 20_000,
                b"{" * 100_000, b" 0" * 200_000]  # fmt: skip
        self.text = TextMutator(self.pristine, BVH_TOKENS, huge)
        self.up = "y"

    def make_input(self, rng: random.Random, index: int) -> bytes:
        self.up = "z" if rng.random() < 0.3 else "y"
        return self.text.mutate(rng)

    def _read(self, path: Path, up: str) -> None:
        from dualhuman_builder.capture.importers.bvh import read_bvh

        read_bvh(path, up=up).save(self.tmp / "skeleton.npz")

    def ops(self, path):
        return [("read_bvh", self._read, (path, self.up))]

    def save(self, data: bytes, esc: Escape, stem: Path):
        paths, doc = super().save(data, esc, stem)
        return paths, dict(doc, up=self.up)


JSON_VALUES: tuple = (None, True, False, 0, -1, 1.5, 10**30, -10**30, 1e308, math.nan, math.inf, "", "x", "\x00\x1b[2J",
                      "/etc/passwd", "/dev/zero", "../../../../etc/passwd", "..", "sequences/../../outside", "C:\\x",
                      "sequences/s0/motion.npz", "manifest.json", "A" * 70_000, [], {}, [1, "a", None], {"a": {"b": []}},
                      [[[[]]]])  # fmt: skip


def mutate_json(rng: random.Random, doc: Any) -> bytes:
    """``doc`` (parsed JSON) with 1 to 3 values replaced (hostile paths, wrong types, huge numbers, NaN), keys
    dropped or added; or its text with one value nested 50,000 levels deep."""
    doc = json.loads(json.dumps(doc))
    slots: list[tuple[Any, Any]] = []

    def walk(node, depth):
        if depth > 12 or len(slots) > 2000:
            return
        items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
        for k, v in items:
            slots.append((node, k))
            walk(v, depth + 1)

    walk(doc, 0)
    if not slots or rng.random() < 0.05:
        return rng.choice((b"[" * 50_000 + b"]" * 50_000, b'{"a":' * 50_000 + b"1" + b"}" * 50_000, b"null", b"",
                           b"\xef\xbb\xbf{}", b"{" + b'"k":1,' * 1000 + b'"k":2}'))  # fmt: skip
    for _ in range(rng.choice((1, 1, 2, 3))):
        node, k = rng.choice(slots)
        try:
            r = rng.random()
            if r < 0.7:
                node[k] = rng.choice(JSON_VALUES)
            elif r < 0.85 and isinstance(node, dict):
                del node[k]
            elif isinstance(node, dict):
                node[rng.choice(("extra", "files", "../x", ""))] = rng.choice(JSON_VALUES)
            else:
                node[k] = [node[k]]
        except (KeyError, IndexError, TypeError):
            pass
    return json.dumps(doc).encode()


class ExportTarget(FileTarget):
    """One file of a small export mutated (the manifest, the schema, a sequence's JSON, an array file, the
    statistics, a split list, the labels), or a file added, then ``verify_export``; the export is restored after."""

    name, suffix = "export", ""

    def __init__(self, tmp: Path, corpus: Path):
        super().__init__(tmp)
        self.root = tmp / "export"
        shutil.copytree(corpus / "export", self.root)
        self.files = {p.relative_to(self.root).as_posix(): p.read_bytes() for p in sorted(self.root.rglob("*")) if p.is_file()}
        self.docs = {rel: json.loads(b) for rel, b in self.files.items() if rel.endswith(".json")}
        self.pristine = None
        self.check_features = True

    def make_input(self, rng: random.Random, index: int) -> dict[str, bytes | None]:
        self.check_features = rng.random() < 0.5
        r = rng.random()
        json_files = sorted(self.docs)
        if r < 0.35:
            rel = "manifest.json"
        elif r < 0.55:
            rel = "schema.json"
        elif r < 0.7:
            rel = rng.choice(json_files)
        elif r < 0.82:
            rel = rng.choice([f for f in self.files if f.endswith(".npz")])
        elif r < 0.87:
            rel = rng.choice([f for f in self.files if f.endswith(".npy")])
        elif r < 0.92:
            rel = rng.choice([f for f in self.files if f.endswith(".txt")])
        elif r < 0.96:
            return {rng.choice(("sequences/s0/extra.npz", "sequences/s9/motion.npz", "extra.json", "splits/val.txt",
                                "stats/x.npy")): rng.randbytes(64)}  # fmt: skip
        else:
            return {rng.choice(list(self.files)): None}  # a member missing
        if rel in self.docs and rng.random() < 0.75:
            return {rel: mutate_json(rng, self.docs[rel])}
        data = self.files[rel]
        if rel.endswith(".npz") and rng.random() < 0.5:  # zip headers: sizes, CRC, offsets
            fields = [f for m in re.finditer(rb"PK\x03\x04", data) for f in
                      ((m.start() + 14, 4, False), (m.start() + 18, 4, False), (m.start() + 22, 4, False),
                       (m.start() + 26, 2, False), (m.start() + 8, 2, False))]  # fmt: skip
            fields += [f for m in re.finditer(rb"PK\x01\x02", data) for f in
                       ((m.start() + 20, 4, False), (m.start() + 24, 4, False), (m.start() + 42, 4, False))]  # fmt: skip
            return {rel: mutate_bytes(rng, data, fields=fields)}
        return {rel: mutate_bytes(rng, data)}

    def run(self, index: int, change: dict[str, bytes | None]) -> list[Escape]:
        from dualhuman_builder.errors import DualhumanError
        from dualhuman_builder.export.verify import verify_export

        made = []
        for rel, data in change.items():
            p = self.root / rel
            if data is None:
                p.unlink(missing_ok=True)
            else:
                if not p.parent.is_dir():
                    made.append(p.parent)
                    p.parent.mkdir(parents=True)
                p.write_bytes(data)
        try:
            e = self.guarded("verify_export", verify_export, self.root, self.check_features, clear=(DualhumanError,))
        finally:
            for rel in change:
                p = self.root / rel
                if rel in self.files:
                    p.write_bytes(self.files[rel])
                else:
                    p.unlink(missing_ok=True)
            for d in made:
                shutil.rmtree(d, ignore_errors=True)
        return [e] if e is not None else []

    def warm(self) -> None:
        self.run(0, {})

    def save(self, change, esc: Escape, stem: Path):
        folder = stem.with_suffix("")
        shutil.rmtree(folder, ignore_errors=True)
        shutil.copytree(self.root, folder)
        for rel, data in change.items():
            if data is None:
                (folder / rel).unlink(missing_ok=True)
            else:
                (folder / rel).parent.mkdir(parents=True, exist_ok=True)
                (folder / rel).write_bytes(data)
        return [folder], {"target": self.name, "file": folder.name, "check_features": self.check_features}

    def replay(self, doc: dict, folder: Path) -> None:
        from dualhuman_builder.export.verify import verify_export

        print("\n".join(verify_export(folder / doc["file"], doc.get("check_features", True))))


CSV_CELLS = (b"", b"T1", b"T2", b"S1", b"T9", b"hug", b"hug;hug", b"nope", b"alice", b"carol", b"ann", b"=1+1",
             b"+cmd|' /C calc'!A0", b"@SUM(1)", b"\x1b[31mred", b"\x00", b"a\nb", b'"', b'""', b'"a""b"',
             b"2026-13-45T99:99:99Z", b"yesterday", b"1e309", b"maybe", b"A" * 140_000, b"\xff\xfe",
             b"T1;T2", "\u202etxt".encode())  # fmt: skip
CSV_TOKENS = [b",", b"\n", b"\r\n", b'"', b",,,,,,,,,,,,", b"extra_col", b"text_9", "\ufeff".encode()]


class AnnotateTarget(FileTarget):
    """``annotate import`` of a mutated CSV or JSON Lines file (``skip_invalid`` on half of them); every 100th
    input also ``annotate export`` in both formats; the workspace is made afresh every 1,000 inputs."""

    name, suffix = "annotate", ".csv"

    def __init__(self, tmp: Path, corpus: Path):
        super().__init__(tmp)
        self.csv = (corpus / "annotations.csv").read_bytes()
        self.jsonl = (corpus / "annotations.jsonl").read_bytes()
        self.csv_text = TextMutator(self.csv, CSV_TOKENS, [b"A" * 140_000, b'"' + b"x" * 140_000, b"," * 100_000])
        self.jsonl_text = TextMutator(self.jsonl, [b"{", b"}", b"[", b'"', b"\n", b"null", b"{}"], [b"[" * 50_000])
        self.ws = None
        self.fmt, self.skip, self.export, self.reset = "csv", False, False, False
        self.pristine = self.csv

    def workspace(self):
        if self.ws is not None:
            self.ws.close()
        shutil.rmtree(self.tmp / "ws", ignore_errors=True)
        self.ws = annotation_workspace(self.tmp / "ws")
        return self.ws

    def make_input(self, rng: random.Random, index: int) -> bytes:
        self.fmt = "jsonl" if rng.random() < 0.5 else "csv"
        self.skip = rng.random() < 0.5
        self.export = index % 100 == 99
        self.reset = index % 1000 == 0
        r = rng.random()
        if self.fmt == "csv":
            if r < 0.5:
                rows = [line.split(b",") for line in self.csv.split(b"\n")]
                for _ in range(rng.choice((1, 1, 2, 4))):
                    row = rng.choice(rows[1:-1])
                    row[rng.randrange(len(row))] = rng.choice(CSV_CELLS)
                return b"\n".join(b",".join(r) for r in rows)
            return self.csv_text.mutate(rng)
        if r < 0.5:
            lines = self.jsonl.split(b"\n")
            k = rng.randrange(len(lines) - 1)
            lines[k] = mutate_json(rng, json.loads(lines[k]))
            return b"\n".join(lines)
        return self.jsonl_text.mutate(rng)

    def _import(self, path: Path) -> None:
        from dualhuman_builder.export.annotate import import_annotations

        import_annotations(self.ws, path, annotator="fz" if self.skip else None, skip_invalid=self.skip)

    def _export(self) -> None:
        from dualhuman_builder.export.annotate import export_annotations

        export_annotations(self.ws, None, "csv")
        export_annotations(self.ws, None, "jsonl")

    def run(self, index: int, data: bytes) -> list[Escape]:
        from dualhuman_builder.errors import DualhumanError

        if self.ws is None or self.reset:
            self.workspace()
        path = self.tmp / f"input.{self.fmt}"
        path.write_bytes(data)
        out = []
        e = self.guarded("import", self._import, path, clear=(DualhumanError,))
        if e is not None:
            out.append(e)
        if self.export:
            e = self.guarded("export", self._export, clear=(DualhumanError,))
            if e is not None:
                out.append(e)
        if out:
            self.workspace()  # a workspace left half-written by an escape is not reused
        return out

    def warm(self) -> None:
        self.export = True
        self.run(0, self.csv)
        self.fmt = "jsonl"
        self.run(0, self.jsonl)
        self.export = False

    def save(self, data: bytes, esc: Escape, stem: Path):
        path = stem.with_suffix("." + self.fmt)
        path.write_bytes(data)
        return [path], {"target": self.name, "file": path.name, "skip_invalid": self.skip}

    def replay(self, doc: dict, folder: Path) -> None:
        from dualhuman_builder.export.annotate import export_annotations, import_annotations

        with tempfile.TemporaryDirectory() as tmp:
            ws = annotation_workspace(Path(tmp) / "ws")
            try:
                print(import_annotations(ws, folder / doc["file"], annotator="fz" if doc.get("skip_invalid") else None,
                                         skip_invalid=doc.get("skip_invalid", False)))  # fmt: skip
                print(export_annotations(ws, None, "csv")[0])
            finally:
                ws.close()


def make_target(name: str, tmp: Path, corpus: Path = CORPUS) -> Target:
    if name in DECODERS:
        return DecoderTarget(name, load_packets(corpus))
    cls = {"take": TakeTarget, "mvnx": MvnxTarget, "bvh": BvhTarget, "export": ExportTarget, "annotate": AnnotateTarget}
    return cls[name](tmp, corpus)


# =============================================================================================== worker
def scratch_dir() -> str | None:
    """Where temporary inputs go: ``/dev/shm`` (memory) when it is writable, else the system's default."""
    shm = Path("/dev/shm")
    return str(shm) if shm.is_dir() and os.access(shm, os.W_OK) else None


def _statm() -> tuple[int, int]:
    """(address space, resident) bytes of this process."""
    size, resident = Path("/proc/self/statm").read_text().split()[:2]
    page = os.sysconf("SC_PAGE_SIZE")
    return int(size) * page, int(resident) * page


def worker(args) -> int:
    """Run inputs ``[start, stop)`` of one target; report on file descriptor ``report_fd`` as JSON lines."""
    warnings.simplefilter("ignore")
    signal.signal(signal.SIGALRM, _alarm)
    report = os.fdopen(args.report_fd, "w", buffering=1)

    def say(**kw) -> None:
        report.write(json.dumps(kw) + "\n")

    at = open(args.index_file, "r+b")
    index_map = mmap.mmap(at.fileno(), 8)
    tmp = Path(tempfile.mkdtemp(prefix=f"{args.worker}-", dir=args.tmp))
    findings = Path(args.findings) / args.worker
    findings.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    try:
        target = make_target(args.worker, tmp, Path(args.corpus))
        target.timeout = args.input_timeout
        if isinstance(target, DecoderTarget):
            target.stop = args.stop
        target.warm()
        if isinstance(target, DecoderTarget):
            target.decoder = None
        vm, baseline = _statm()
        cap = vm + args.memory_mib * 2**20
        resource.setrlimit(resource.RLIMIT_AS, (cap, cap))
        say(ready=True, baseline_kib=baseline // 1024, setup_s=round(time.perf_counter() - t_start, 2))
        counts: dict[str, Counter] = {"escaped": Counter(), "caught": Counter()}
        first: dict[str, dict[str, dict]] = {"escaped": {}, "caught": {}}
        n_caught = inputs = units = harness_errors = 0

        def note(esc: Escape, i: int, inp, kind: str) -> None:
            """Count ``esc``; the first of its kind is reported, and saved as a reproducer while few are."""
            counts[kind][esc.key] += 1
            if esc.key in first[kind]:
                return
            info = {"key": esc.key, "op": esc.op, "type": esc.type, "where": esc.where, "message": esc.message,
                    "index": i, "reproducer": None}  # fmt: skip
            if len(first[kind]) < KEEP:
                prefix = "" if kind == "escaped" else "caught-"
                stem = findings / f"{args.start:06d}-{prefix}{len(first[kind]) + 1:02d}-{esc.op}-{esc.type}"
                try:
                    _, doc = target.save(inp, esc, stem)
                    doc.update({k: v for k, v in info.items() if k != "reproducer"})
                    doc.update({"kind": kind, "seed": args.seed, "trace": esc.trace})
                    side = stem.with_suffix(".json")
                    side.write_text(json.dumps(doc, indent=1) + "\n")
                    info["reproducer"] = side.relative_to(ROOT).as_posix() if side.is_relative_to(ROOT) else str(side)
                except (OSError, MemoryError) as e:
                    info["reproducer"] = f"not saved: {e}"
            first[kind][esc.key] = info
            say(**{"finding" if kind == "escaped" else "caught": info})

        def snapshot() -> dict:
            return {"inputs": inputs, "units": units, "counts": dict(counts["escaped"]),
                    "caught": n_caught, "caught_counts": dict(counts["caught"]), "seconds": round(time.perf_counter() - t0, 3),
                    "cpu_s": round(time.process_time() - c0, 3), "harness_errors": harness_errors}  # fmt: skip

        t0 = last = time.perf_counter()
        c0 = time.process_time()
        for i in range(args.start, args.stop):
            index_map[:8] = struct.pack("<q", i)
            rng = random.Random(f"{args.seed}:{args.worker}:{i}")
            try:
                inp = target.make_input(rng, i)
                if isinstance(inp, list):
                    units += len(inp)
                escapes = target.run(i, inp)
                caught, n = list(getattr(target, "caught", ())), getattr(target, "caught_count", 0)
            except Exception:  # noqa: BLE001 - outside the guarded operations: a fault of this script, not an escape
                harness_errors += 1
                if harness_errors <= 3:
                    say(harness_error=traceback.format_exc(), index=i)
                continue
            n_caught += n
            for esc in escapes:
                note(esc, i, inp, "escaped")
            for esc in caught:
                note(esc, i, inp, "caught")
            inputs += 1
            now = time.perf_counter()
            if now - last > 2.0:
                say(progress=True, **snapshot())
                last = now
        target.close()
        usage = resource.getrusage(resource.RUSAGE_SELF)
        say(done=True, maxrss_kib=usage.ru_maxrss, **snapshot())
        return 0
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


# =============================================================================================== parent
class Shard:
    """Inputs ``[start, stop)`` of one target, run by one worker process at a time (restarted after the input
    that killed it)."""

    def __init__(self, target: str, start: int, stop: int):
        self.target, self.start, self.stop = target, start, stop
        self.next = start
        self.proc: subprocess.Popen | None = None
        self.fd = -1
        self.buf = b""
        self.index_file: Path | None = None
        self.snapshot: dict | None = None  # the running worker's latest counts
        self.got_done = False
        self.watchdog = False
        self.results: list[dict] = []  # one per worker process: inputs, units, counts, seconds
        self.crashes: list[dict] = []
        self.done_inputs = 0
        self.last_index, self.last_change = -1, time.monotonic()
        self.maxrss_kib = 0
        self.baseline_kib = 0
        self.restarts = 0
        self.finished = False


class Runner:
    """Starts the shards' workers, ``--jobs`` at a time, reads their reports, restarts a worker that died, kills
    one that is stuck in one input, and prints progress on stderr."""

    def __init__(self, args):
        self.args = args
        self.run_dir = Path(tempfile.mkdtemp(prefix="fuzz-run-", dir=scratch_dir()))  # workers' files; removed at the end
        self.sel = selectors.DefaultSelector()
        self.findings: dict[str, dict[str, dict]] = {t: {} for t in args.targets}
        self.caught: dict[str, dict[str, dict]] = {t: {} for t in args.targets}
        self.t0 = time.monotonic()
        self.logs = CACHE / "fuzz" / "logs"
        self.logs.mkdir(parents=True, exist_ok=True)

    def log(self, text: str) -> None:
        print(f"[{time.monotonic() - self.t0:6.0f} s] {text}", file=sys.stderr, flush=True)

    @property
    def stall_s(self) -> float:
        return max(60.0, 4 * self.args.input_timeout)

    def start(self, sh: Shard) -> None:
        a = self.args
        r, w = os.pipe()
        sh.index_file = self.run_dir / f"{sh.target}-{sh.start}.index"
        sh.index_file.write_bytes(struct.pack("<q", sh.next))
        env = dict(os.environ, OMP_NUM_THREADS="1", OPENBLAS_NUM_THREADS="1", MKL_NUM_THREADS="1",
                   NUMEXPR_NUM_THREADS="1", PYTHONHASHSEED="0")  # fmt: skip
        log = open(self.logs / f"{sh.target}-{sh.start:06d}.log", "ab" if sh.restarts else "wb")
        cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", sh.target, "--start", str(sh.next),
               "--stop", str(sh.stop), "--seed", str(a.seed), "--report-fd", str(w), "--index-file", str(sh.index_file),
               "--corpus", str(a.corpus), "--findings", str(a.findings), "--memory-mib", str(a.memory_mib),
               "--input-timeout", str(a.input_timeout), "--tmp", str(self.run_dir)]  # fmt: skip
        sh.proc = subprocess.Popen(cmd, pass_fds=(w,), stdin=subprocess.DEVNULL, stdout=log, stderr=log, env=env, cwd=ROOT)
        log.close()
        os.close(w)
        os.set_blocking(r, False)
        sh.fd, sh.buf, sh.snapshot, sh.got_done, sh.watchdog = r, b"", None, False, False
        sh.last_index, sh.last_change = sh.next - 1, time.monotonic()
        self.sel.register(r, selectors.EVENT_READ, sh)

    def handle(self, sh: Shard, msg: dict) -> None:
        if "finding" in msg:
            f = msg["finding"]
            known = self.findings[sh.target]
            if f["key"] not in known:
                self.log(f"{sh.target}: escaped at input {f['index']}: {f['key']}: {f['message'][:160]}"
                         + (f" -> {f['reproducer']}" if f.get("reproducer") else ""))  # fmt: skip
            if f["key"] not in known or f["index"] < known[f["key"]]["index"]:
                known[f["key"]] = f
        elif "caught" in msg and isinstance(msg["caught"], dict):
            f = msg["caught"]
            known = self.caught[sh.target]
            if f["key"] not in known:
                self.log(f"{sh.target}: the decoder's guard caught, at input {f['index']}: {f['key']}: {f['message'][:120]}")
            if f["key"] not in known or f["index"] < known[f["key"]]["index"]:
                known[f["key"]] = f
        elif "progress" in msg or "done" in msg:
            sh.snapshot = msg
            sh.got_done = "done" in msg
        elif "ready" in msg:
            sh.baseline_kib = max(sh.baseline_kib, msg["baseline_kib"])
        elif "harness_error" in msg:  # the input is skipped; the run goes on
            self.log(f"{sh.target}: fault of the fuzz script at input {msg['index']} (input skipped):\n{msg['harness_error']}")

    def reap(self, sh: Shard) -> None:
        """The worker closed its report pipe: collect it; after a death, count it and go on after its input."""
        self.sel.unregister(sh.fd)
        os.close(sh.fd)
        _, status, usage = os.wait4(sh.proc.pid, 0)
        sh.maxrss_kib = max(sh.maxrss_kib, usage.ru_maxrss, (sh.snapshot or {}).get("maxrss_kib", 0))
        snap = dict(sh.snapshot or {"inputs": 0, "units": 0, "counts": {}, "seconds": 0.0})
        if os.WIFEXITED(status) and os.WEXITSTATUS(status) == 0 and sh.got_done:
            sh.results.append(snap)
            sh.done_inputs += snap["inputs"]
            sh.finished = True
            return
        last = struct.unpack("<q", sh.index_file.read_bytes()[:8])[0]
        why = (f"killed by signal {signal.Signals(os.WTERMSIG(status)).name}" if os.WIFSIGNALED(status)
               else f"exit status {os.WEXITSTATUS(status)}")  # fmt: skip
        if sh.watchdog:
            why = f"hang: no progress for {self.stall_s:.0f} s, killed"
        if not sh.snapshot and last < sh.next:  # died during set-up: nothing to go on with
            self.log(f"{sh.target}: worker failed to start ({why}); see {self.logs}/{sh.target}-{sh.start:06d}.log")
            sh.finished = True
            return
        key = f"worker: died ({why})"
        self.log(f"{sh.target}: worker died at input {last} ({why}); log {self.logs}/{sh.target}-{sh.start:06d}.log")
        snap["inputs"] = last - sh.next + 1
        sh.results.append(snap)
        sh.crashes.append({"key": key, "index": last})
        self.findings[sh.target].setdefault(key, {"key": key, "op": "worker", "type": why.split(":")[0], "where": "-",
                                                  "message": why, "index": last, "reproducer": None})  # fmt: skip
        sh.done_inputs += snap["inputs"]
        sh.next = last + 1
        sh.restarts += 1
        if sh.next >= sh.stop or sh.restarts > 20:
            sh.finished = True
        else:
            self.start(sh)

    def run(self, shards: list[Shard]) -> None:
        pending = list(shards)
        running: list[Shard] = []
        last_report = time.monotonic()
        while pending or running:
            while pending and len(running) < self.args.jobs:
                sh = pending.pop(0)
                self.start(sh)
                running.append(sh)
            for key, _ in self.sel.select(timeout=1.0):
                sh = key.data
                try:
                    chunk = os.read(sh.fd, 1 << 16)
                except BlockingIOError:
                    continue
                if chunk:
                    sh.buf += chunk
                    *lines, sh.buf = sh.buf.split(b"\n")
                    for line in lines:
                        self.handle(sh, json.loads(line))
                else:
                    self.reap(sh)
                    if sh.finished:
                        running.remove(sh)
            now = time.monotonic()
            for sh in running:  # the watchdog: a worker stuck in one input past its time limit
                idx = struct.unpack("<q", sh.index_file.read_bytes()[:8])[0]
                if idx != sh.last_index:
                    sh.last_index, sh.last_change = idx, now
                elif now - sh.last_change > self.stall_s and sh.proc.poll() is None:
                    sh.watchdog = True
                    sh.proc.kill()
            if now - last_report > self.args.report_s:
                last_report = now
                self.status(shards)
        self.status(shards)

    def status(self, shards: list[Shard]) -> None:
        per: dict[str, list[int]] = {}
        for sh in shards:
            p = per.setdefault(sh.target, [0, 0])
            p[0] += sh.done_inputs + (0 if sh.finished or not sh.snapshot else sh.snapshot["inputs"])
            p[1] += sh.stop - sh.start
        self.log("; ".join(f"{t} {d:,}/{n:,}" + (f" ({len(self.findings[t])} kinds escaped)" if self.findings[t] else "")
                           for t, (d, n) in per.items()))  # fmt: skip


def plan(targets: list[str], inputs: int) -> list[Shard]:
    """Shards of at most :data:`SHARD` inputs, the file readers first (they are slower), targets interleaved."""
    per = {t: [Shard(t, a, min(a + SHARD, inputs)) for a in range(0, inputs, SHARD)] for t in targets}
    order = [t for t in targets if t in READERS] + [t for t in targets if t not in READERS]
    out = []
    for k in range(max((len(v) for v in per.values()), default=0)):
        out += [per[t][k] for t in order if k < len(per[t])]
    return out


def _listed(kinds: dict[str, dict], counts: Counter) -> list[dict]:
    for k, n in counts.items():
        kinds.setdefault(k, {"key": k, "message": "", "index": None, "reproducer": None})["count"] = n
    listed = sorted((f for f in kinds.values() if f.get("count")), key=lambda f: (-f["count"], f["key"]))[:LISTED]
    return [{k: f.get(k) for k in ("key", "count", "message", "index", "reproducer")} for f in listed]


def summarise(args, shards: list[Shard], runner: Runner, wall_s: float) -> dict:
    """The results file's figures: per target inputs, escapes (and, for decoders, the exceptions their guard
    caught), peak memory, time, and every kind of escape with its count, first input and reproducer."""
    figures: dict[str, Any] = {"targets": {}, "wall_s": round(wall_s, 1)}
    for t in args.targets:
        mine = [s for s in shards if s.target == t]
        counts: Counter = Counter()
        caught: Counter = Counter()
        seconds = cpu = units = 0.0
        n_caught = inputs = harness = 0
        for s in mine:
            for r in s.results:
                counts.update(r.get("counts", {}))
                caught.update(r.get("caught_counts", {}))
                n_caught += r.get("caught", 0)
                seconds += r.get("seconds", 0.0)
                cpu += r.get("cpu_s", 0.0)
                harness += r.get("harness_errors", 0)
                units += r.get("units", 0)
            for c in s.crashes:
                counts[c["key"]] += 1
            inputs += s.done_inputs
        escapes = _listed(runner.findings[t], counts)
        guard = _listed(runner.caught[t], caught)
        decoder = t in DECODERS
        figures["targets"][t] = {
            "kind": "decoder" if decoder else "reader", "url": DECODERS.get(t), "inputs": inputs,
            "packets": int(units) if decoder else None, "escaped": sum(counts.values()), "kinds": len(counts),
            "hangs": sum(n for k, n in counts.items() if ": hang at" in k or "(hang" in k),
            "worker_deaths": sum(len(s.crashes) for s in mine), "harness_errors": harness,
            "caught": n_caught if decoder else None, "caught_kinds": len(caught) if decoder else None,
            "peak_mib": round(max((s.maxrss_kib for s in mine), default=0) / 1024, 1),
            "baseline_mib": round(max((s.baseline_kib for s in mine), default=0) / 1024, 1),
            "seconds": round(seconds, 1), "cpu_s": round(cpu, 1), "ms_per_input": round(1000 * seconds / max(inputs, 1), 3),
            "cpu_ms_per_input": round(1000 * cpu / max(inputs, 1), 3),
            "first": "none" if not escapes else f"{escapes[0]['key']} ({escapes[0]['count']:,}x)",
            "first_caught": None if not decoder else "none" if not guard else f"{guard[0]['key']} ({guard[0]['count']:,}x)",
            "findings": escapes, "caught_findings": guard if decoder else None,
        }  # fmt: skip
    return figures


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter,
                                 epilog=__doc__.split("\n\n", 1)[1])  # fmt: skip
    ap.add_argument("--inputs", type=int, default=None, help=f"inputs per target (default {DEFAULT_INPUTS:,})")
    ap.add_argument("--quick", action="store_true", help=f"{QUICK_INPUTS:,} inputs per target: a smoke run")
    ap.add_argument("--targets", default=",".join(TARGETS), help=f"comma-separated, of {', '.join(TARGETS)}")
    ap.add_argument("--seed", type=int, default=0, help="input i of target T is drawn from (seed, T, i)")
    ap.add_argument("--jobs", type=int, default=os.cpu_count() or 1, help="worker processes at a time (default: cores)")
    ap.add_argument("--memory-mib", type=int, default=MEMORY_MIB,
                    help=f"goal and cap: MiB a worker may grow beyond its set-up (default {MEMORY_MIB})")
    ap.add_argument("--input-timeout", type=float, default=INPUT_TIMEOUT_S, help="seconds one operation may take")
    ap.add_argument("--out", type=Path, default=None, help="results file (default benchmarks/results/fuzz.json)")
    ap.add_argument("--corpus", type=Path, default=CORPUS, help="corpus folder (made when missing)")
    ap.add_argument("--findings", type=Path, default=FINDINGS, help="reproducers go to FINDINGS/<target>/")
    ap.add_argument("--report-s", type=float, default=30.0, help="seconds between progress lines on stderr")
    ap.add_argument("--replay", type=Path, default=None, help="run a saved finding again (its .json) and show what escapes")
    ap.add_argument("--build-corpus", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--start", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--stop", type=int, default=0, help=argparse.SUPPRESS)
    ap.add_argument("--report-fd", type=int, default=-1, help=argparse.SUPPRESS)
    ap.add_argument("--index-file", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--tmp", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)

    if args.worker:
        return worker(args)
    if args.build_corpus:
        build_corpus(args.corpus, progress=lambda m: print(m, file=sys.stderr, flush=True))
        return 0
    if args.replay:
        return replay(args.replay)
    args.corpus, args.findings = args.corpus.resolve(), args.findings.resolve()  # the workers run in the repository
    args.targets = [t.strip() for t in args.targets.split(",") if t.strip()]
    unknown = [t for t in args.targets if t not in TARGETS]
    if unknown:
        ap.error(f"unknown target(s) {', '.join(unknown)}; choose from {', '.join(TARGETS)}")
    inputs = args.inputs if args.inputs is not None else QUICK_INPUTS if args.quick else DEFAULT_INPUTS
    if inputs <= 0:
        ap.error("--inputs must be positive")
    if not (args.corpus / "packets.npz").is_file():
        r = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--build-corpus", "--corpus", str(args.corpus)],
                           cwd=ROOT, check=False)  # fmt: skip
        if r.returncode:
            print("fuzz: the corpus could not be made", file=sys.stderr)
            return 1
    for t in args.targets:
        shutil.rmtree(args.findings / t, ignore_errors=True)
    shards = plan(args.targets, inputs)
    runner = Runner(args)
    runner.log(f"fuzzing {', '.join(args.targets)}: {inputs:,} inputs each, seed {args.seed}, {len(shards)} worker runs, "
               f"{args.jobs} at a time")  # fmt: skip
    t0 = time.monotonic()
    try:
        runner.run(shards)
    finally:
        shutil.rmtree(runner.run_dir, ignore_errors=True)
    figures = summarise(args, shards, runner, time.monotonic() - t0)
    for t, f in figures["targets"].items():
        guard = f"  guard caught {f['caught']:,} ({f['caught_kinds']} kinds)" if f["caught"] is not None else ""
        print(f"{t:<9} {f['inputs']:>8,} inputs  {f['escaped']:>7,} escaped ({f['kinds']} kinds){guard}  peak "
              f"{f['peak_mib']:7.1f} MiB  {f['seconds']:7.1f} s  most frequent: {f['first']}")  # fmt: skip
    goals = []
    for t in args.targets:
        goals += [Goal(f"targets.{t}.escaped", "<=", 0, label=f"{t}: exceptions escaped"),
                  Goal(f"targets.{t}.inputs", ">=", DEFAULT_INPUTS, label=f"{t}: inputs tried"),
                  Goal(f"targets.{t}.peak_mib", "<=", args.memory_mib, "MiB", label=f"{t}: peak memory of its process")]  # fmt: skip
    tables = [Table("Per target", ["target", "inputs", "escaped", "kinds", "caught by the decoder's guard", "peak MiB",
                                   "CPU ms per input"],
                    [[t, f"targets.{t}.inputs", f"targets.{t}.escaped", f"targets.{t}.kinds", f"targets.{t}.caught",
                      f"targets.{t}.peak_mib", f"targets.{t}.cpu_ms_per_input"] for t in args.targets]),
              Table("The most frequent escape per target (and, for a decoder, the exception its guard caught most)",
                    ["target", "escaped: operation: exception at where (count)", "caught by the guard"],
                    [[t, f"targets.{t}.first", f"targets.{t}.first_caught"] for t in args.targets])]  # fmt: skip
    notes = (f"The run took {figures['wall_s'] / 60:.1f} minutes. Each target ran in its own worker processes "
             f"({args.jobs} at a time, up to {SHARD:,} inputs each), the address space capped at its size after set-up "
             f"plus {args.memory_mib} MiB, each operation limited to {args.input_timeout:g} s; peak memory is the largest "
             "ru_maxrss of a target's processes. The results file lists every kind of escape (and of exception a "
             "decoder's guard caught) with its count, first input and a reproducer under benchmarks/cache/fuzz-findings/ "
             "(not committed): `.venv/bin/python benchmarks/fuzz.py --replay FINDING.json` runs it again. "
             "`--targets NAME --inputs N` fuzzes one target; `--quick` runs 1,000 inputs per target.")  # fmt: skip
    params = {"inputs": inputs, "targets": args.targets, "seed": args.seed, "jobs": args.jobs,
              "memory_mib": args.memory_mib, "input_timeout_s": args.input_timeout, "session": SESSION,
              "corpus": corpus_digest(args.corpus)}  # fmt: skip
    path = write_results("fuzz", figures, params=params, goals=goals, tables=tables, notes=notes, out=args.out)
    print(f"written {path}")
    return 0


def replay(side: Path) -> int:
    """Run the input of a saved finding again, in this process, and show the exception it raises."""
    from dualhuman_builder.errors import DualhumanError

    doc = json.loads(side.read_text())
    warnings.simplefilter("ignore")
    signal.signal(signal.SIGALRM, _alarm)
    print(f"{doc['target']}: {doc.get('key', '')} (input {doc.get('index')}, seed {doc.get('seed')})")
    with tempfile.TemporaryDirectory() as tmp:
        try:
            if doc["target"] in DECODERS:
                from dualhuman_builder.capture.sources import RawPacket, make_decoder

                dec = make_decoder(doc["url"])
                for t, h in doc["packets"]:
                    dec.feed(RawPacket(int(t), bytes.fromhex(h)))
                dec.finish()
            else:
                cls = {"take": TakeTarget, "mvnx": MvnxTarget, "bvh": BvhTarget, "export": ExportTarget,
                       "annotate": AnnotateTarget}[doc["target"]]  # fmt: skip
                target = cls.__new__(cls)
                FileTarget.__init__(target, Path(tmp))
                target.out, target.up = Path(tmp) / "repaired.mcap", doc.get("up", "y")
                target.replay(doc, side.parent)
        except DualhumanError as e:
            if doc["target"] in DECODERS:
                traceback.print_exc()
                return 1
            print(f"a clear error ({type(e).__name__}): {e}")
        except Exception:  # noqa: BLE001 - showing it is the point
            traceback.print_exc()
            return 1
    print("nothing escaped")
    return 0


if __name__ == "__main__":
    sys.exit(main())

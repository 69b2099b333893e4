"""Replay a take: to the pipeline (the recorded samples, bit for bit) or back onto the wire.

* :func:`replay_samples` yields the decoded samples exactly as they were recorded (same values,
  same order, same device and host timestamps); :func:`replay_packets` the raw packets.
* :func:`redecode` runs the raw packets through fresh decoders built from the recorded source
  URLs; :func:`verify_replay` checks that this gives the recorded samples bit for bit (the
  decoders are deterministic), so a take can be re-decoded by a newer toolkit and compared. It
  also counts the samples the raw bytes hold that the take does not (its decoded samples lag the
  raw bytes after a crash or a full disk: ``dualhuman log repair`` writes them), and the damage
  met reading the take; a file without take metadata is refused with a FormatError.
* :func:`replay_to` puts the raw packets back on real transports at the recorded timing divided
  by ``speed`` (``math.inf``: as fast as possible): ``mvn+udp://HOST:PORT`` and
  ``vive+udp://HOST:PORT`` send each recorded datagram of the MVN / VIVE sources as one datagram,
  ``xbus://PATH`` writes the recorded serial bytes to a port (a device path or pyserial URL),
  ``mti+can://INTERFACE/CHANNEL`` sends the recorded CAN frames. A consumer on the other side sees
  the same bytes with the same spacing as from the live devices.
"""

from __future__ import annotations

import math
import socket
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator
from urllib.parse import urlsplit

import numpy as np

from dualhuman_builder.capture.log.reader import TakeReader
from dualhuman_builder.capture.log.schemas import MESSAGE_ENCODING
from dualhuman_builder.capture.log.writer import entity_of
from dualhuman_builder.capture.sources import RawPacket, SourceError, make_decoder
from dualhuman_builder.errors import FormatError

#: Which recorded source kinds each ``--to`` scheme carries.
TARGET_KINDS = {"mvn+udp": "mvn", "vive+udp": "vive", "xbus": "xbus", "mti+can": "mti-can"}


def replay_samples(path: str | Path) -> Iterator[tuple[str, object]]:
    """``(source name, sample)`` as recorded, in recorded order."""
    return TakeReader(path).samples()


def replay_packets(path: str | Path) -> Iterator[tuple[str, RawPacket]]:
    """``(source name, raw packet)`` as recorded, in recorded order."""
    return TakeReader(path).raw_packets()


def _take_sources(reader: TakeReader) -> list[dict]:
    """The ``sources`` of a take's metadata (name, url, kind); FormatError for a file without them."""
    reader.load_header()
    meta = reader.take_meta()
    sources = meta.get("sources")
    named = isinstance(sources, list) and all(isinstance(s, dict) and isinstance(s.get("name"), str)
                                              and isinstance(s.get("url"), str) for s in sources)  # fmt: skip
    if "take" not in reader.metadata or not named:
        raise FormatError("the file has no take metadata naming its sources: it was not recorded by "
                          "`dualhuman capture`", path=reader.path,
                          fix="replay and verify takes recorded by `dualhuman capture`; read other MCAP files "
                              "with the mcap CLI or Foxglove")  # fmt: skip
    return sources


def redecode(path: str | Path, problems: list[str] | None = None) -> Iterator[tuple[str, object]]:
    """The raw packets decoded again by fresh decoders (one per recorded source URL). FormatError
    for a file without take metadata; raw packets of a source the metadata does not name are
    counted in ``problems`` (when given), as is the damage met reading the take."""
    reader = TakeReader(path)
    decoders = {s["name"]: make_decoder(s["url"]) for s in _take_sources(reader)}
    unknown: Counter = Counter()
    packets = TakeReader(path)
    for name, packet in packets.raw_packets():
        dec = decoders.get(name)
        if dec is None:
            unknown[name] += 1
            continue
        for s in dec.feed(packet):
            yield name, s
    for name, dec in decoders.items():
        for s in dec.finish():
            yield name, s
    if problems is not None:
        problems += packets.problems
        problems += [f"{n} raw packets of source {name!r}, which the take's metadata does not name, not decoded"
                     for name, n in sorted(unknown.items())]  # fmt: skip


def same_sample(a, b) -> bool:
    """Whether two samples are the same type with bit-identical fields (arrays compared by shape,
    dtype and bytes, so NaNs compare equal to themselves)."""
    if type(a) is not type(b):
        return False
    for k, v in vars(a).items() if hasattr(a, "__dict__") else ():
        w = getattr(b, k)
        if isinstance(v, np.ndarray):
            if v.shape != w.shape or v.dtype != w.dtype or v.tobytes() != np.asarray(w).tobytes():
                return False
        elif v != w:
            return False
    return True


@dataclass
class ReplayCheck:
    """What :func:`verify_replay` found. ``samples``: recorded samples compared with a re-decoded
    one, ``mismatches`` of them differing (``first_mismatch`` says which); ``missing``: re-decoded
    samples beyond the recorded ones of their source (the decoded samples lag the raw bytes:
    ``dualhuman log repair`` writes them); ``unreproduced``: recorded samples beyond the re-decoded
    ones; ``problems``: damage met reading the take."""

    samples: int
    mismatches: int
    first_mismatch: str | None
    missing: int = 0
    unreproduced: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def identical(self) -> bool:
        """Every recorded sample re-decoded bit for bit, and nothing more."""
        return self.mismatches == 0 and self.missing == 0 and self.unreproduced == 0

    @property
    def verified(self) -> bool:
        """Identical, on an undamaged take holding at least one sample."""
        return self.identical and self.samples > 0 and not self.problems


def _describe(s) -> str:
    return f"{type(s).__name__} of {entity_of(s)} at host time {getattr(s, 'host_time_ns', '?')} ns"


def verify_replay(path: str | Path) -> ReplayCheck:
    """Re-decode the raw packets and compare with the recorded samples, source by source in
    recorded order, bit for bit (float arrays compared by their bytes, NaNs included). FormatError
    for a file without take metadata (see :func:`redecode`)."""
    problems: list[str] = []
    remaining: Counter = Counter()  # recorded samples per source: from the summary's statistics, else counted
    counter = TakeReader(path)
    stats = counter.summary.statistics if counter.summary is not None and not counter.summary.problems else None
    if stats is not None and counter.scan.complete:
        for cid, n in stats.channel_message_counts.items():
            ch = counter.channels.get(cid)
            if ch is not None and ch.message_encoding == MESSAGE_ENCODING:
                remaining[ch.metadata.get("source", "")] += n
    else:
        for ch, _ in counter.messages():
            if ch.message_encoding == MESSAGE_ENCODING:
                remaining[ch.metadata.get("source", "")] += 1
        problems += counter.problems
    reader = TakeReader(path)
    recorded = reader.samples()
    again = redecode(path, problems)
    queues: dict[str, deque] = {}
    check = ReplayCheck(0, 0, None, problems=problems)
    exhausted = False
    for name, b in again:
        if remaining[name] <= 0 and not queues.get(name):
            check.missing += 1
            continue
        q = queues.setdefault(name, deque())
        while not q and not exhausted:
            got = next(recorded, None)
            if got is None:
                exhausted = True
                break
            remaining[got[0]] -= 1
            queues.setdefault(got[0], deque()).append(got[1])
        if not q:
            check.missing += 1
            continue
        a = q.popleft()
        check.samples += 1
        if not same_sample(a, b):
            check.mismatches += 1
            if check.first_mismatch is None:
                check.first_mismatch = (f"sample {check.samples} of source {name!r}: recorded {_describe(a)}, "
                                        f"re-decoded {_describe(b)}")  # fmt: skip
    check.unreproduced = sum(len(q) for q in queues.values()) + sum(1 for _ in recorded)
    problems += reader.problems
    if not reader.scan.complete:
        problems.append("the take has no index (summary and footer): the recording did not finish — "
                        "run `dualhuman log repair`")  # fmt: skip
    check.problems = list(dict.fromkeys(problems))
    return check


# ---------------------------------------------------------------------- back onto the wire
class _Target:
    def __init__(self, url: str):
        self.url = url
        parts = urlsplit(url)
        self.scheme = parts.scheme
        if self.scheme not in TARGET_KINDS:
            raise SourceError(f"cannot replay to {url!r}", fix=f"use one of {', '.join(s + '://' for s in TARGET_KINDS)}")
        self.kind = TARGET_KINDS[self.scheme]
        self.sent = 0
        self.errors = 0
        if self.scheme in ("mvn+udp", "vive+udp"):
            if parts.hostname is None or parts.port is None:
                raise SourceError(f"{url!r} needs HOST:PORT", fix=f"e.g. {self.scheme}://127.0.0.1:9763")
            self.address = (parts.hostname, parts.port)
            self.sock = socket.socket(socket.AF_INET6 if ":" in parts.hostname else socket.AF_INET, socket.SOCK_DGRAM)
            self.send = self._udp
        elif self.scheme == "xbus":
            import serial

            target = parts.path if not parts.netloc else f"{parts.netloc}://"
            self.port = serial.serial_for_url(target, baudrate=921600, timeout=0, write_timeout=5)
            self.send = self._serial
        else:
            import can

            interface, channel = parts.netloc, parts.path.lstrip("/")
            self.bus = can.Bus(interface=interface, channel=channel)
            self.send = self._can

    def _udp(self, data: bytes) -> None:
        try:
            self.sock.sendto(data, self.address)
            self.sent += 1
        except OSError:
            self.errors += 1

    def _serial(self, data: bytes) -> None:
        self.port.write(data)
        self.sent += 1

    def _can(self, data: bytes) -> None:
        from dualhuman_builder.capture.wire.mti_can import unpack_can_frame

        self.bus.send(unpack_can_frame(data))
        self.sent += 1

    def close(self) -> None:
        for attr, fn in (("sock", "close"), ("port", "close"), ("bus", "shutdown")):
            if hasattr(self, attr):
                getattr(getattr(self, attr), fn)()


@dataclass
class ReplayReport:
    packets: int = 0
    sent: Counter = field(default_factory=Counter)
    errors: int = 0
    skipped_sources: list[str] = field(default_factory=list)
    elapsed_s: float = 0.0
    recorded_s: float = 0.0


def replay_to(path: str | Path, targets: list[str], *, speed: float = 1.0, stop: Callable[[], bool] | None = None,
              progress: Callable[[int], None] | None = None) -> ReplayReport:  # fmt: skip
    """Send the raw packets of ``path`` to ``targets`` (see the module docstring) at the recorded
    timing divided by ``speed``. Streams the file (memory does not grow with the take)."""
    if not speed > 0:
        raise SourceError(f"speed must be > 0 (inf: as fast as possible), got {speed}")
    kinds = {s["name"]: s.get("kind") for s in _take_sources(TakeReader(path))}
    opened = [_Target(u) for u in targets]
    by_kind = {t.kind: t for t in opened}
    report = ReplayReport(skipped_sources=sorted(n for n, k in kinds.items() if k not in by_kind))
    start = time.perf_counter()
    t0 = None
    last = None
    try:
        for name, p in TakeReader(path).raw_packets():
            target = by_kind.get(kinds.get(name))
            if target is None:
                continue
            if t0 is None:
                t0 = p.host_time_ns
            if math.isfinite(speed):
                delay = start + (p.host_time_ns - t0) / 1e9 / speed - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            target.send(p.data)
            report.packets += 1
            last = p.host_time_ns
            if progress is not None and report.packets % 1000 == 0:
                progress(report.packets)
            if stop is not None and stop():
                break
    finally:
        for t in opened:
            report.sent[t.url] = t.sent
            report.errors += t.errors
            t.close()
    report.elapsed_s = time.perf_counter() - start
    report.recorded_s = 0.0 if t0 is None else (last - t0) / 1e9
    return report
